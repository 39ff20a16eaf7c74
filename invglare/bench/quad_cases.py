"""Per-size benchmark cases of the quad-based Fourier transform (Scandolo, Lee & Eisemann 2018).

The paper's four apertures (:mod:`invglare.optics.quad.apertures`), its tables measured here:

- **far field** (fig. 10, Table 2): ``quad_far_{aperture}`` with culling (below 1e-7 of the
  peak) and symmetry, an N/2 raster to an N output at the FFT's own pixel scale, against
  the FFT floor and invglare's FFT and MFT paths of the same raster (``quad_ref_fft``,
  ``quad_ref_mft``); the heptagon also without either, with culling only and with symmetry
  only (``quad_table2_{none,cull,sym}``);
- **progressive** (fig. 3, 10): ``quad_prog_{aperture}`` is one frame of the paper's
  animation (a circular shadow moving over the aperture, 5 px per frame at a 512 px raster,
  back and forth) by difference quads, ``quad_prog_full_{aperture}`` the same frame from
  scratch (quadtree and evaluation); both include building the frame's quadtrees;
- **spectral** (Table 3): 60 wavelengths over 400-700 nm from an N x N heptagon PSF, full
  scaling (``quad_spectral_full``, 60 resamplings) and batch scaling
  (``quad_spectral_batch``, 4 + 15);
- **near field** (Table 4): ``quad_near_{aperture}``, an N raster observed on its own grid
  at a Fresnel number of 10 by closed-form Fresnel integrals, against the alias-free
  discrete near field, the angular spectrum zero-padded 8x (``quad_near_padded``; like the
  paper's GPU-NFD it does not run at N = 2048, whose 16384^2 arrays do not fit here).
"""

from __future__ import annotations

import math

import numpy as np

from invglare.bench.cases import Case
from invglare.optics.quad.apertures import PAPER_APERTURES

LAM = 550.0
#: Culling threshold of the benchmarked far field (fraction of the peak intensity).
CULL = 1e-7
FRESNEL_NUMBER = 10.0

#: Table 1 of the paper: quads of its apertures at 256^2 .. 4096^2.
PAPER_TABLE1 = {
    "box": (40, 40, 40, 617, 617),
    "circle": (109, 227, 440, 981, 1976),
    "heptagon": (176, 389, 730, 1613, 2996),
    "whirl": (303, 647, 1358, 2673, 5278),
}
#: Table 2 (heptagon far field, ms on a GTX 1080 Ti) at 256^2 .. 4096^2.
PAPER_TABLE2 = {
    "none": (0.13, 0.40, 2.25, 19.46, 139.35),
    "cull": (0.21, 0.32, 1.06, 5.65, 31.63),
    "sym": (0.14, 0.25, 1.20, 9.76, 74.70),
    "both": (0.14, 0.26, 0.71, 3.57, 20.22),
}
#: Table 3 (spectral scaling, ms): full and batch.
PAPER_TABLE3 = {
    "full": (0.040, 0.127, 0.530, 1.960, 8.180),
    "batch": (0.019, 0.038, 0.114, 0.430, 1.710),
}
#: Table 4 (near field, ms): GPU-NFD (8x padded) and the paper's NFD per aperture.
PAPER_TABLE4 = {
    "padded": (4.87, 20.94, 94.73, None, None),
    "box": (0.12, 0.14, 0.28, 7.88, 30.88),
    "circle": (0.11, 0.23, 0.84, 5.43, 41.30),
    "heptagon": (0.14, 0.36, 1.71, 15.78, 137.16),
    "whirl": (0.16, 0.49, 2.93, 23.42, 255.72),
}
PAPER_SIZES = (256, 512, 1024, 2048, 4096)


def _raster_and_grid(name: str, n: int):
    from invglare.optics.quad.apertures import paper_grid, paper_raster

    return paper_raster(name, n).astype(np.float32), paper_grid(n)


def _propagator(grid, npix: int, method: str, options=None, **kwargs):
    from invglare.optics.propagator import make_propagator

    return make_propagator(
        window_mm=float(grid.width_mm),
        focal_length_mm=kwargs.pop("focal_length_mm", 17.0),
        fft_wavelength_nm=LAM,
        shortest_wavelength_nm=LAM,
        npix=npix,
        aperture_npix=grid.npix,
        method=method,
        method_options=options,
        **kwargs,
    )


def _call(prop, raster):
    import jax
    import jax.numpy as jnp

    field = jnp.asarray(raster)
    run = jax.jit(lambda p, f: p(f, LAM))
    return lambda: run(prop, field)


def _far(name: str, cull: bool, symmetry: bool):
    def make(n: int):
        import jax.numpy as jnp

        raster, grid = _raster_and_grid(name, n // 2)
        options = {"cull_below": CULL if cull else 0.0, "symmetry": "auto" if symmetry else "none"}
        prop = _propagator(grid, n, "quad", options).prepared(jnp.asarray(raster))
        return _call(prop, raster)

    return make


def _reference(method: str):
    def make(n: int):
        raster, grid = _raster_and_grid("heptagon", n // 2)
        scale = math.degrees(LAM * 1e-6 / (n * float(grid.pitch_mm)))
        prop = _propagator(grid, n, method, pixel_scale_deg=scale)
        return _call(prop, raster)

    return make


def shadow_frames(name: str, n: int):
    """The paper's animation on an `n` px raster: a shadow of a sixth of the raster's width
    moving by 5 px per frame at 512 px (scaled), back and forth over 60 frames."""
    from invglare.optics.quad.progressive import moving_shadow

    raster, grid = _raster_and_grid(name, n)
    speed = 5.0 * n / 512
    frame = moving_shadow(
        raster.astype(np.float64), n / 12, (n * 0.2, n * 0.45), (speed, 0.3 * speed)
    )
    return (lambda t: frame(29.5 - abs(t % 60 - 29.5))), grid


def _progressive(name: str, full: bool):
    def make(n: int):
        from invglare._core.grids import AngularGrid
        from invglare.optics.quad.progressive import ProgressiveQuads

        frame, grid = shadow_frames(name, n // 2)
        out = AngularGrid(n, math.degrees(LAM * 1e-6 / (n * float(grid.pitch_mm))))
        prog = ProgressiveQuads(grid, out, LAM)
        prog.psf(frame(0))
        state = {"t": 0}

        def step():
            state["t"] += 1
            raster = frame(state["t"])
            return prog.full_psf(raster) if full else prog.psf(raster)

        return step

    return make


def _spectral(batch: bool):
    def make(n: int):
        import jax
        import jax.numpy as jnp

        from invglare.optics.quad.spectral import (
            BatchPlan,
            batch_scaled_copies,
            full_scaled_copies,
        )

        raster, grid = _raster_and_grid("heptagon", n // 2)
        prop = _propagator(grid, n, "quad").prepared(jnp.asarray(raster))
        psf = jax.jit(lambda p, r: p(r, LAM))(prop, jnp.asarray(raster))
        plan = BatchPlan.build(400.0, 700.0, 60)
        run = jax.jit(lambda p: (batch_scaled_copies if batch else full_scaled_copies)(p, plan))
        return lambda: run(psf)

    return make


def near_distance_mm() -> float:
    """The distance of a Fresnel number ``(D/2)^2 / (lambda z)`` of 10 for the 4 mm aperture."""
    from invglare.optics.quad.apertures import DIAMETER_MM

    return (DIAMETER_MM / 2) ** 2 / (LAM * 1e-6 * FRESNEL_NUMBER)


def _near(name: str):
    def make(n: int):
        import jax.numpy as jnp

        raster, grid = _raster_and_grid(name, n)
        d = near_distance_mm()
        scale = math.degrees(float(grid.pitch_mm) / d)
        prop = _propagator(
            grid, n, "quad", propagation="fresnel", focal_length_mm=d, pixel_scale_deg=scale
        ).prepared(jnp.asarray(raster))
        return _call(prop, raster)

    return make


#: Largest N of the 8x padded near field (its arrays are 8N a side: 8192^2 complex64 is
#: 512 MB each, several at once).
MAX_PADDED = 1024


def _near_padded(n: int):
    if n > MAX_PADDED:
        return None
    import jax
    import jax.numpy as jnp

    from invglare.optics.fresnel import angular_spectrum

    raster, grid = _raster_and_grid("heptagon", n)
    d = near_distance_mm()
    field = jnp.asarray(raster, jnp.complex64)

    @jax.jit
    def run(f):
        u = angular_spectrum(f, grid, LAM, d, pad_npix=8 * n, kind="fresnel")
        return (u.real**2 + u.imag**2) / jnp.sum(jnp.abs(f) ** 2)

    return lambda: run(field)


QUAD_CASES: tuple[Case, ...] = (
    *(
        Case(
            f"quad_far_{name}",
            "pipeline",
            f"quad far field of the {name} (N/2 raster to N, culling below {CULL:g} of the "
            "peak and symmetry)",
            _far(name, True, True),
        )
        for name in PAPER_APERTURES
    ),
    *(
        Case(
            f"quad_table2_{variant}",
            "pipeline",
            f"quad far field of the heptagon, {label} (Table 2)",
            _far("heptagon", cull, sym),
        )
        for variant, label, cull, sym in (
            ("none", "no culling, no symmetry", False, False),
            ("cull", "culling only", True, False),
            ("sym", "symmetry only", False, True),
        )
    ),
    Case(
        "quad_ref_fft",
        "pipeline",
        "invglare's FFT path of the same raster (padded to N)",
        _reference("fft"),
    ),
    Case(
        "quad_ref_mft",
        "pipeline",
        "invglare's MFT path of the same raster and sampling",
        _reference("mft"),
    ),
    *(
        Case(
            f"quad_prog{'_full' if full else ''}_{name}",
            "pipeline",
            f"one frame of the moving shadow over the {name}, "
            + ("from scratch" if full else "by difference quads (progressive)"),
            _progressive(name, full),
        )
        for name in PAPER_APERTURES
        for full in (False, True)
    ),
    Case(
        "quad_spectral_full",
        "pipeline",
        "60 wavelengths by full scaling (Table 3)",
        _spectral(False),
    ),
    Case(
        "quad_spectral_batch",
        "pipeline",
        "60 wavelengths by batch scaling, 4 + 15 (Table 3)",
        _spectral(True),
    ),
    *(
        Case(
            f"quad_near_{name}",
            "pipeline",
            f"quad near field of the {name} (N raster on its own grid, Fresnel number 10)",
            _near(name),
        )
        for name in PAPER_APERTURES
    ),
    Case(
        "quad_near_padded",
        "pipeline",
        "alias-free discrete near field: angular spectrum padded 8x (the paper's GPU-NFD)",
        _near_padded,
    ),
)

#: Progressive case -> the full evaluation of the same frames: timed together by the
#: runner, their calls alternating, since their ratio is the result (Table 2's speed-up).
PROGRESSIVE_PAIRS: dict[str, str] = {
    f"quad_prog_{name}": f"quad_prog_full_{name}" for name in PAPER_APERTURES
}


def _ratio_cell(a: float | None, b: float | None) -> str:
    return f"{a / b:.1f}x" if a and b else ""


def quad_markdown(records: list[dict]) -> list[str]:
    """bench.md's quad section: Tables 2-4 beside the paper's, and the issue's goals."""
    by_key = {(r["case"], r["size"]): r for r in records}
    sizes = sorted({r["size"] for r in records if r["case"].startswith("quad_")})
    if not sizes:
        return []

    def ms(case, n):
        r = by_key.get((case, n))
        return None if r is None else r["median_ms"]

    def paper(table, key, n):
        if n not in PAPER_SIZES:
            return None
        return table[key][PAPER_SIZES.index(n)]

    def cell(v):
        return "" if v is None else f"{v:.2f}"

    lines = ["## Quad-based Fourier transform (Scandolo et al. 2018)", ""]
    lines += [
        "Median ms here (2 CPU cores, float32) beside the paper's (GTX 1080 Ti). `x floor`: "
        "over the fastest bare N x N FFT of the same run.",
        "",
        "| case | N | ms here | x floor | paper ms |",
        "|---|---:|---:|---:|---:|",
    ]
    for name in PAPER_APERTURES:
        for n in sizes:
            r = by_key.get((f"quad_far_{name}", n))
            if r:
                lines.append(
                    f"| quad_far_{name} | {n} | {r['median_ms']:.2f} | {cell(r['ratio'])} | |"
                )
    def paper_rows(title: str, table: dict, case_of, with_ratio: bool = False):
        """One row per variant and N measured here, beside the paper's value."""
        for key in table:
            case = case_of(key)
            for n in sizes:
                if ms(case, n) is None:
                    continue
                label = f"{title} {key} ({case})" if with_ratio else f"{title} {key}"
                ratio = f" {cell(by_key[(case, n)]['ratio'])} " if with_ratio else " "
                lines.append(
                    f"| {label} | {n} | {cell(ms(case, n))} |{ratio}| "
                    f"{cell(paper(table, key, n))} |"
                )

    paper_rows(
        "Table 2", PAPER_TABLE2,
        lambda v: "quad_far_heptagon" if v == "both" else f"quad_table2_{v}", with_ratio=True,
    )  # fmt: skip
    paper_rows("Table 3", PAPER_TABLE3, lambda v: f"quad_spectral_{v}")
    paper_rows(
        "Table 4", PAPER_TABLE4,
        lambda k: "quad_near_padded" if k == "padded" else f"quad_near_{k}",
    )  # fmt: skip
    lines += [
        "",
        "Ratios measured side by side in this run (a progressive frame and the same frame "
        "from scratch timed together, their calls alternating):",
        "",
    ]
    lines += [
        "| N | aperture | far / floor | far / fft path | far / mft path | progressive "
        "speed-up | near speed-up vs padded |",
        "|---:|---|---:|---:|---:|---:|---:|",
    ]
    for n in sizes:
        for name in PAPER_APERTURES:
            far = by_key.get((f"quad_far_{name}", n))
            lines.append(
                f"| {n} | {name} | {cell(far['ratio']) if far else ''} | "
                f"{_ratio_cell(ms(f'quad_far_{name}', n), ms('quad_ref_fft', n))} | "
                f"{_ratio_cell(ms(f'quad_far_{name}', n), ms('quad_ref_mft', n))} | "
                f"{_ratio_cell(ms(f'quad_prog_full_{name}', n), ms(f'quad_prog_{name}', n))} | "
                f"{_ratio_cell(ms('quad_near_padded', n), ms(f'quad_near_{name}', n))} |"
            )
    return lines
