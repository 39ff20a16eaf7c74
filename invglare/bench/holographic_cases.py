"""Benchmark cases of the holographic eye against the paper's timings (Novosad & Ziegler).

The paper reports CPU seconds per rendering (Pentium IV 3.6 GHz with a GeForce 8800 GTX;
the point-source evaluation on the CPU), RGB, one point source per pixel:

| table | scene                    | size | iterations | base | + lashes | + lashes, tear film |
|------:|--------------------------|-----:|-----------:|-----:|---------:|--------------------:|
| 3.1   | teapot (depth buffer)    | 256  | 16         | 39   | 58       | 75                  |
| 3.1   | teapot (depth buffer)    | 512  | 16         | 245  | 314      | 382                 |
| 3.1   | teapot (depth buffer)    | 512  | 64         | 975  | 1269     | 1563                |
| 3.3   | HDR car (constant depth) | 256  | 16         | 153  | 171      | 191                 |
| 3.3   | HDR car (constant depth) | 512  | 64         | 5031 | 5453     | 5645                |

The cases render an ``N x N`` RGB HDR frame (the bundled street-lights scene) through the
same eye at the paper's size and iterations (16 at 256, 64 at 512, as in both tables):
a 3 mm pupil, lids and 40 upper lashes 8 mm in front of it, a random tear film at the
cornea, the lens focused at the scene's 2 m, R, G, B at 640, 550, 460 nm, an ``N x N`` grid whose
window is 8 mm at 460 nm. Each case is one jitted call of
:meth:`~invglare.models.holographic.HolographicEye.render` (the layers' rasters, the
transfer functions and every iteration; the model is built before timing):

- ``holo_{base,lashes,lashes_tear}``: constant depth (2 m), as the paper's Table 3.3;
- ``holo_depth_{base,lashes,lashes_tear}``: a depth buffer from 0.5 to 20 m in 8 vergence
  layers (the paper's Table 3.1 has a depth buffer; its layer count is not given);
- ``holo_speckle_free`` / ``holo_depth_speckle_free``: the limit of infinitely many
  iterations (:meth:`~invglare.models.holographic.HolographicEye.speckle_free_image`) with
  all layers and 2 x 2 PSF tiles per depth layer: the fast mode. It costs a stack pass
  per tile and depth layer (32 with 8 layers), against a pass per iteration;
- ``holo_fft_floor`` / ``holo_depth_fft_floor``: the bare complex FFTs of ``N x N`` that
  ``holo_lashes_tear`` and ``holo_depth_lashes_tear`` would need with every layer on the
  whole grid (6 and 13 per channel and iteration), in batches of three. The model runs the
  layers on the part of the grid the pupil's light crosses (a cropped stack, 80-256 of
  512 samples here) with pruned base and retina transforms, so it can go below this.

The goal (the issue): at least 300 times faster than the paper on 2 CPU cores at the same
size, iterations and layers; 512 x 512 x 64 with all layers in at most 5 s with a constant
depth (paper: 1563-5645 s) and 20 s with 8 depth layers. :func:`paper_markdown` tabulates
the measured medians beside the paper's seconds.
"""

from __future__ import annotations

import numpy as np

from invglare.bench.cases import Case

#: Iterations of the paper's rows by size (both tables).
PAPER_ITERATIONS = {256: 16, 512: 64}
#: The layers of the paper's three columns, as the model's switches.
LAYER_SETS = {
    "base": ("pupil", "lens"),
    "lashes": ("lashes", "pupil", "lens"),
    "lashes_tear": ("lashes", "tear_film", "pupil", "lens"),
}
#: Paper seconds by (table, size, iterations) and column.
PAPER_S = {
    ("3.1", 256, 16): {"base": 39, "lashes": 58, "lashes_tear": 75},
    ("3.1", 512, 16): {"base": 245, "lashes": 314, "lashes_tear": 382},
    ("3.1", 512, 64): {"base": 975, "lashes": 1269, "lashes_tear": 1563},
    ("3.3", 256, 16): {"base": 153, "lashes": 171, "lashes_tear": 191},
    ("3.3", 512, 64): {"base": 5031, "lashes": 5453, "lashes_tear": 5645},
}
#: Depth layers of the depth-buffer cases.
DEPTH_LAYERS = 8
#: PSF tiles per axis of the speckle-free cases: 2 x 2 exact PSFs per depth layer, blended.
SPECKLE_FREE_TILES = 2
#: FFTs of N x N per channel and iteration: base inverse FFT(s), 2 per angular-spectrum
#: step, 1 to the retina.
FFTS_PER_ITERATION = {"constant": 6, "depth": 5 + DEPTH_LAYERS}
_GOAL = "goal <= 5 s (constant depth) / 20 s (8 depth layers) at 512 x 64 on 2 cores"


def bench_model(n: int, layers: str, depth: bool, iterations: int | None = None):
    """The benchmark eye on an ``n x n`` grid (see the module docstring)."""
    from invglare.aperture.eye import EyeAperture, Eyelashes, Eyelids, Pupil
    from invglare.models.holographic import HolographicEye
    from invglare.optics.holographic import Frustum, TearFilm

    eye = EyeAperture(
        pupil=Pupil(3.0),
        lids=Eyelids(1.6, 1.8, 0.0, 0.0, 0.04),
        upper_lashes=Eyelashes(
            count=40.0, n_max=48, key=7, lid="upper", angular_spread_deg=12.0,
            thickness_mm=0.06, length_mm=2.5, curvature_per_mm=0.05, root_span_mm=8.0,
        ),
    )  # fmt: skip
    depth_mm = scene_depth_mm(n)
    return HolographicEye.build(
        eye,
        npix=n,
        window_mm=8.0,
        focus_distance_mm=depth_mm,
        depth_mm=depth_mm,
        tear_film=TearFilm(0.1, 0.4, key=3, pattern="random"),
        layers=LAYER_SETS[layers],
        frustum=Frustum(near_mm=1e3 * 0.5, far_mm=20000.0),
        depth_layers=DEPTH_LAYERS if depth else 1,
        iterations=PAPER_ITERATIONS.get(n, 16) if iterations is None else iterations,
        psf_tiles=SPECKLE_FREE_TILES,
    )


def nearest_depth_mm(n: int) -> float:
    """The nearest depth the benchmark eye's ``n x n`` grid resolves (its lash plane at 8 mm).

    As :meth:`~invglare.models.holographic.HolographicEye.nearest_depth_mm`, for the 3 mm
    pupil, written out so that the inputs need no model: about 227 mm at 256, 120 mm at 512.
    """
    half_field = 0.5 * n * 460e-6 / 8.0
    need = 1.5 + 8.0 * half_field + 2 * 8.0 / n
    return 8.0 + need / half_field


def scene_depth_mm(n: int) -> float:
    """The constant depth of the cases: 2 m, or farther on grids too small to resolve it."""
    return max(2000.0, 1.5 * nearest_depth_mm(n))


def bench_inputs(n: int, depth: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """An ``n x n`` RGB HDR frame (street lights at night) and, if asked, its depth (m)."""
    from invglare.render.scenes import street_lights_at_night

    frame, _ = street_lights_at_night(n, seed=0)
    if not depth:
        return np.asarray(frame), None
    # Near at the bottom of the frame (the road), far at the top: 0.5 m to 20 m (from 1.5 x
    # the nearest resolvable depth on grids too small for 0.5 m).
    near_m = max(0.5, 1.5e-3 * nearest_depth_mm(n))
    rows = np.linspace(1.0, 0.0, n)[:, None] * np.ones((1, n))
    return np.asarray(frame), (near_m * (20.0 / near_m) ** rows).astype(np.float32)


def _render_case(layers: str, depth: bool, mode: str = "iterations"):
    def make(n: int):
        import equinox as eqx

        model = bench_model(n, layers, depth)
        frame, depth_buf = bench_inputs(n, depth)
        if mode == "speckle_free":
            run = eqx.filter_jit(lambda m, f, d: m.speckle_free_image(f, d))
            return lambda: run(model, frame, depth_buf)
        run = eqx.filter_jit(lambda m, f, d, k: m.render(f, d, k))
        import jax

        key = jax.random.key(0)
        return lambda: run(model, frame, depth_buf, key)

    return make


def _fft_floor(depth: bool):
    def make(n: int):
        import jax
        import jax.numpy as jnp

        count = FFTS_PER_ITERATION["depth" if depth else "constant"]
        iterations = PAPER_ITERATIONS.get(n, 16)
        rng = np.random.default_rng(0)
        x = jnp.asarray(
            (rng.standard_normal((3, n, n)) + 1j * rng.standard_normal((3, n, n))).astype(
                np.complex64
            )
        )

        @jax.jit
        def ffts(x):
            def body(y, _):
                return jnp.fft.fft2(y) * (1.0 / n), None

            y, _ = jax.lax.scan(body, x, None, length=count * iterations)
            return y

        return lambda: ffts(x)

    return make


def _rows() -> list[Case]:
    cases = []
    for prefix, depth, table in (("holo", False, "3.3"), ("holo_depth", True, "3.1")):
        for layers in LAYER_SETS:
            paper = ", ".join(
                f"{n}^2 x {it}: {PAPER_S[(table, n, it)][layers]} s"
                for n, it in PAPER_ITERATIONS.items()
            )
            what = "constant depth" if not depth else f"depth buffer, {DEPTH_LAYERS} layers"
            cases.append(
                Case(
                    f"{prefix}_{layers}",
                    "pipeline",
                    f"holographic eye, {layers.replace('_', ' + ')} ({what}), RGB, "
                    f"{PAPER_ITERATIONS.get(256)} iterations at 256 / "
                    f"{PAPER_ITERATIONS.get(512)} at 512; paper Table {table}: {paper}; {_GOAL}",
                    _render_case(layers, depth),
                )
            )
        cases.append(
            Case(
                f"{prefix}_speckle_free",
                "pipeline",
                f"holographic eye, all layers, speckle-free limit "
                f"({SPECKLE_FREE_TILES} x {SPECKLE_FREE_TILES} PSF tiles per depth layer), "
                f"{'constant depth' if not depth else f'{DEPTH_LAYERS} depth layers'}",
                _render_case("lashes_tear", depth, "speckle_free"),
            )
        )
        cases.append(
            Case(
                f"{prefix}_fft_floor",
                "pipeline",
                f"the {FFTS_PER_ITERATION['depth' if depth else 'constant']} x 3 x iterations "
                f"bare N^2 complex FFTs {prefix}_lashes_tear would need on the whole grid",
                _fft_floor(depth),
            )
        )
    return cases


HOLOGRAPHIC_CASES: tuple[Case, ...] = tuple(_rows())


def paper_markdown(records: list[dict]) -> list[str]:
    """bench.md's table: each holographic case's median beside the paper's seconds."""
    by_key = {(r["case"], r["size"]): r["median_ms"] for r in records}
    rows = []
    for prefix, table in (("holo", "3.3"), ("holo_depth", "3.1")):
        for n, iterations in PAPER_ITERATIONS.items():
            floor = by_key.get((f"{prefix}_fft_floor", n))
            for layers in LAYER_SETS:
                ms = by_key.get((f"{prefix}_{layers}", n))
                if ms is None:
                    continue
                paper_s = PAPER_S[(table, n, iterations)][layers]
                ratio = paper_s * 1e3 / ms
                vs_floor = f"{ms / floor:.2f}" if floor and layers == "lashes_tear" else ""
                rows.append(
                    f"| {table} | {prefix}_{layers} | {n} | {iterations} | {paper_s} | "
                    f"{ms / 1e3:.2f} | {ratio:.0f}x | {vs_floor} |"
                )
            free = by_key.get((f"{prefix}_speckle_free", n))
            if free is not None:
                rows.append(
                    f"| {table} | {prefix}_speckle_free | {n} | (limit) | "
                    f"{PAPER_S[(table, n, iterations)]['lashes_tear']} | {free / 1e3:.2f} | "
                    f"{PAPER_S[(table, n, iterations)]['lashes_tear'] * 1e3 / free:.0f}x | |"
                )
    if not rows:
        return []
    return [
        "## Holographic eye against Novosad & Ziegler",
        "",
        "Median seconds here (this machine, its load in the records) beside the paper's "
        "(Pentium IV 3.6 GHz, CPU point-source evaluation); `x floor` is the median over the "
        "bare FFTs the rendering needs (`*_fft_floor`, same run).",
        "",
        "| table | case | N | iterations | paper s | s here | faster | x floor |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
        *rows,
    ]
