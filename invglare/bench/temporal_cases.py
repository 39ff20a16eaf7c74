"""Benchmark cases of the temporal glare model: is a frame real time on a CPU?

Ritschel et al. (2009, Table 2) report, on a GeForce 8800 GTX (2008), PSFs with 2x2
aperture super-sampling and 32 spectral samples, *without* convolution:

| size | aperture | diffraction | display | overall |
|-----:|---------:|------------:|--------:|--------:|
| 256  | 5.2 ms   | 2.7 ms      | 1.1 ms  | 9.0 ms  |
| 512  | 11.8 ms  | 4.8 ms      | 1.8 ms  | 18.4 ms |
| 1024 | 36.5 ms  | 13.8 ms     | 4.8 ms  | 55.1 ms |

The cases time one frame of an animation in steady state, as
:func:`~invglare.render.temporal_frames.render_sequence` runs it: the paper's
night eye (750 lens-nucleus and 250 vitreous particles, 200 gratings, lids and 80
lashes), default dynamics, an N/2 aperture raster padded to an N x N FFT. What is
computed once per sequence (the particles and gratings that do not
move, the lids and lashes while no blink is under way, and the spectrum of a still
frame) is computed before timing; everything a frame needs is timed:

- ``temporal_psf``: dynamics step and values, the moving particles and the pupil
  rasterised, eq. 3 at the eye's 17 mm (the model's default, alias-free: the aperture's
  N x N transform, the Fresnel kernel, the inverse transform; the paper multiplied by a
  stored ``E`` and took one FFT), 32 scaled copies into linear RGB (the paper's "overall");
- ``temporal_frame``: that, plus the FFT convolution of an N x N RGB frame (zero-padded
  to avoid wrap-around: transforms of 1.5N x 1.5N, see `linear_period`) and the gamma 2.2
  tone map;
- ``temporal_frame_wrap``: the same with a circular convolution on the frame's N x N
  grid, as a texture-based GPU pipeline does (light leaving one edge re-enters at the
  other).

Where a frame's time goes is timed stage by stage (``temporal_stage_*``, each stage
jitted alone on the previous stage's output; their sum can differ a little from the frame,
which XLA compiles as one program): the dynamics step and the aperture, the monochrome
PSF (eq. 3: transform, Fresnel kernel, inverse transform, normalisation), the 32 scaled
copies into RGB, the convolution
(transform of the PSF, product with the frame's stored spectrum, inverse transform) and
the tone map. :func:`stage_markdown` tabulates them beside the frame.

Sizes above 1024 are skipped (the paper stops there).
"""

from __future__ import annotations

import numpy as np

from invglare.bench.cases import Case

#: The stages of ``temporal_frame``, in order: case-name suffix and what it times.
STAGES = (
    ("aperture", "dynamics step + moving aperture"),
    ("mono_psf", "eq. 3 at 17 mm: FFT, Fresnel kernel, inverse FFT"),
    ("copies", "32 scaled copies into linear RGB"),
    ("convolve", "PSF transform, product, inverse transform"),
    ("tonemap", "gamma 2.2"),
)

#: Ritschel et al. (2009) Table 2, overall ms per PSF (no convolution), by size.
PAPER_TABLE2_MS = {256: 9.0, 512: 18.4, 1024: 55.1}
_PAPER = "paper (GeForce 8800 GTX, no convolution): 9.0 / 18.4 / 55.1 ms at 256 / 512 / 1024"
_MAX_N = 1024


def _model(n: int):
    import dataclasses

    from invglare.aperture.eye import night_eye
    from invglare.models.temporal import TemporalGlare

    eye = night_eye(0)
    # The preset's 40 um gratings need a pitch <= 20 um, finer than any N/2 raster here has
    # (the model refuses a grating its raster aliases): they keep their count and lines,
    # at the finest spacing the raster resolves (what a frame costs does not depend on it).
    probe = TemporalGlare.build(dataclasses.replace(eye, gratings=None), npix=n)
    pitch = float(probe.propagator.grid.pitch_mm)
    spacing = max(float(eye.gratings.spacing_mm), 2.5 * pitch)
    gratings = dataclasses.replace(eye.gratings, spacing_mm=spacing)
    return TemporalGlare.build(dataclasses.replace(eye, gratings=gratings), npix=n)


def _psf_case(n: int):
    if n > _MAX_N:
        return None
    import equinox as eqx

    model = _model(n)
    constants = eqx.filter_jit(lambda m: m.sequence_constants())(model)
    state = model.init_state(1.0)

    @eqx.filter_jit
    def frame(m, c, s):
        return m.advance(s, 1.0), m.psf_cf(c, s)

    return lambda: frame(model, constants, state)


def _frame_inputs(n: int, wrap: bool):
    """The night eye, a random N x N RGB frame, the sequence constants, the frame's stored
    spectrum and a resting state: what a frame of an animation starts from."""
    import equinox as eqx
    import jax.numpy as jnp

    from invglare.render.temporal_frames import frame_convolver

    model = _model(n)
    rng = np.random.default_rng(3)
    image = jnp.asarray(rng.random((n, n, 3)) * 10.0, jnp.float32)
    constants = eqx.filter_jit(lambda m: m.sequence_constants())(model)
    spectrum = eqx.filter_jit(lambda m, i: frame_convolver(m, i, None, wrap)[0])(model, image)
    return model, image, constants, spectrum, model.init_state(1.0)


def _frame_case(wrap: bool):
    def make(n: int):
        if n > _MAX_N:
            return None
        import equinox as eqx

        from invglare.render.temporal_frames import display, frame_convolver

        model, image, constants, spectrum, state = _frame_inputs(n, wrap)

        @eqx.filter_jit
        def frame(m, c, s, spec, img):
            _, glare = frame_convolver(m, img, None, wrap)
            return m.advance(s, 1.0), display(m, glare(spec, m.psf_cf(c, s)))

        return lambda: frame(model, constants, state, spectrum, image)

    return make


def _stage_case(stage: str):
    def make(n: int):
        if n > _MAX_N:
            return None
        import equinox as eqx
        import jax

        from invglare.render.temporal_frames import display, frame_convolver

        model, image, consts, spectrum, state = _frame_inputs(n, wrap=False)

        def aperture(m, c, s):
            return m.advance(s, 1.0), m._aperture(c, m.frame_values(s))

        def convolve(m, spec, psf):  # as in temporal_frame: the frame's spectrum is stored
            return frame_convolver(m, image, None, False)[1](spec, psf)

        # Each stage: (model, what it needs besides its input, the previous stage's output).
        steps = {
            "aperture": (aperture, consts),
            "mono_psf": (lambda m, c, ap: m._mono_psf(c, ap), consts),
            "copies": (lambda m, _, mono: m._spectral_cf(mono), None),
            "convolve": (convolve, spectrum),
            "tonemap": (lambda m, _, linear: display(m, linear), None),
        }
        value = state
        for name, _ in STAGES:  # run the stages before this one once, for its input
            fn, aux = eqx.filter_jit(steps[name][0]), steps[name][1]
            if name == stage:
                return lambda: fn(model, aux, value)
            value = fn(model, aux, value)
            value = value[1] if name == "aperture" else jax.block_until_ready(value)
        raise AssertionError(stage)

    return make


def stage_markdown(records: list[dict]) -> list[str]:
    """bench.md's table of a temporal frame's stages (ms, share of their sum), per N."""
    by_key = {(r["case"], r["size"]): r["median_ms"] for r in records}
    sizes = sorted({n for (case, n) in by_key if case.startswith("temporal_stage_")})
    if not sizes:
        return []
    names = [name for name, _ in STAGES]
    lines = [
        "## Temporal frame: where the time goes",
        "",
        "Each stage jitted alone (`temporal_stage_*`), median ms and share of the stages' "
        "sum; `temporal_frame` is the whole frame as one program.",
        "",
        "| N | " + " | ".join(names) + " | sum | temporal_frame |",
        "|---:|" + "---:|" * (len(names) + 2),
    ]
    for n in sizes:
        times = [by_key.get((f"temporal_stage_{name}", n)) for name in names]
        total = sum(t for t in times if t is not None)
        cells = [f"{t:.1f} ({100 * t / total:.0f} %)" if t else "" for t in times]
        frame = by_key.get(("temporal_frame", n))
        lines.append(
            f"| {n} | "
            + " | ".join(cells)
            + f" | {total:.1f} | "
            + (f"{frame:.1f}" if frame else "")
            + " |"
        )
    return lines


TEMPORAL_CASES: tuple[Case, ...] = (
    Case(
        "temporal_psf",
        "pipeline",
        "temporal glare PSF per frame: dynamics + moving aperture (N/2) + Fresnel FFT (N) + "
        f"32 scaled copies to RGB; {_PAPER}",
        _psf_case,
    ),
    Case(
        "temporal_frame",
        "pipeline",
        "temporal glare full frame: temporal_psf + padded FFT convolution of an N x N RGB "
        "still frame + gamma 2.2; goal <= 33 ms at N = 512 on 2 cores",
        _frame_case(wrap=False),
    ),
    Case(
        "temporal_frame_wrap",
        "pipeline",
        "temporal_frame with circular (unpadded, GPU-texture-like) convolution",
        _frame_case(wrap=True),
    ),
    *(
        Case(
            f"temporal_stage_{name}",
            "pipeline",
            f"temporal_frame stage: {what} (jitted alone)",
            _stage_case(name),
        )
        for name, what in STAGES
    ),
)
