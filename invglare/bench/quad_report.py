"""``reports/quad/`` (committed): the quad-based transform beside Scandolo, Lee & Eisemann (2018).

Run after ``invglare bench quad --out-dir reports/quad`` (whose ``bench.json`` holds the
timings of Tables 2-4)::

    python -m invglare.bench.quad_report --out-dir reports/quad   # default: runs/quad

It measures what is not a timing (Table 1's quad counts, the fig. 8 quality metrics, the
culling and progressive errors, a fit with the polygon method against the MFT), draws the
figures (plain PNGs: the quadtree of fig. 1a, far and near fields, fig. 3's difference
quads, fig. 8's grid) and writes ``report.md`` with the paper's numbers beside ours and
the issue's goals met or not, from the timings of that run.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np

from invglare.bench.quad_cases import (
    CULL,
    LAM,
    PAPER_SIZES,
    PAPER_TABLE1,
    PAPER_TABLE2,
    PAPER_TABLE3,
    PAPER_TABLE4,
    near_distance_mm,
    shadow_frames,
)
from invglare.bench.runner import cpu_line
from invglare.optics.quad.apertures import PAPER_APERTURES, paper_grid, paper_raster
from invglare.optics.quad.progressive import PIXEL_QUADS_UP_TO

DECADES = 6.0
#: Near fields span far less: shown over two decades.
NEAR_DECADES = 2.0


# ------------------------------------------------------------------------------ images


def _log_image(psf: np.ndarray, peak: float | None = None, decades: float = DECADES) -> np.ndarray:
    """``log10(psf / peak)`` from `-decades` to 0 as magma RGB, the field's y up."""
    from matplotlib import colormaps

    peak = float(np.max(psf)) if peak is None else peak
    scaled = np.clip(1.0 + np.log10(np.maximum(psf / peak, 1e-12)) / decades, 0.0, 1.0)
    return colormaps["magma"](scaled[::-1])[..., :3]


def _grey(raster: np.ndarray) -> np.ndarray:
    return np.repeat(0.25 + 0.5 * np.clip(raster[::-1], 0, 1)[..., None], 3, axis=-1)


def _outline(image: np.ndarray, y0, x0, h, w, colour, scale: int) -> None:
    """Draw rectangles (pixel units of the raster; image rows flipped) in place."""
    n = image.shape[0] // scale
    for a, b, c, d in zip(y0, x0, h, w, strict=True):
        top, bottom = (n - (a + c)) * scale, (n - a) * scale - 1
        left, right = b * scale, (b + d) * scale - 1
        image[top : bottom + 1, [left, right]] = colour
        image[[top, bottom], left : right + 1] = colour


def _magnified(image: np.ndarray, scale: int) -> np.ndarray:
    return np.repeat(np.repeat(image, scale, axis=0), scale, axis=1)


def quadtree_figure(raster: np.ndarray, layout, scale: int = 4) -> np.ndarray:
    """Fig. 1a: the aperture (grey) and its quads: white squares, cyan 2:1 quads, red
    negative quads."""
    image = _magnified(_grey(raster), scale)
    kinds = (
        (layout.sign > 0) & (layout.w == layout.h),
        (layout.sign > 0) & (layout.w != layout.h),
        layout.sign < 0,
    )
    for mask, colour in zip(
        kinds, ((1.0, 1.0, 1.0), (0.2, 0.9, 0.9), (1.0, 0.2, 0.2)), strict=True
    ):
        _outline(image, layout.y0[mask], layout.x0[mask], layout.h[mask], layout.w[mask],
                 colour, scale)  # fmt: skip
    return image


def _strip(panels: list[np.ndarray], gap: int = 4) -> np.ndarray:
    h = max(p.shape[0] for p in panels)
    out = []
    for p in panels:
        if p.shape[0] < h:  # centre a smaller panel vertically
            pad = h - p.shape[0]
            p = np.pad(p, ((pad // 2, pad - pad // 2), (0, 0), (0, 0)), constant_values=1.0)
        out += [p, np.ones((h, gap, 3))]
    return np.concatenate(out[:-1], axis=1)


# ---------------------------------------------------------------------------- measures


def table1_counts(sizes=PAPER_SIZES) -> dict[str, dict[int, dict[str, int]]]:
    """Quads per aperture and raster size: the soft raster from pixels (exact) and from
    2x2 means (the paper's half-size start), and the binary raster (coverage >= 0.5) from
    2x2 means thresholded again (closest to the paper's own inputs)."""
    from invglare.optics.quad import build_quadtree

    out: dict[str, dict[int, dict[str, int]]] = {}
    for name in PAPER_APERTURES:
        out[name] = {}
        for n in sizes:
            raster = paper_raster(name, n)
            half = raster.reshape(n // 2, 2, n // 2, 2).mean(axis=(1, 3))
            out[name][n] = {
                "soft": build_quadtree(raster).n_quads,
                "soft_half": build_quadtree(raster, base_level=1).n_quads,
                "binary_half": build_quadtree((half >= 0.5).astype(float), band=None).n_quads,
            }
    return out


def _quad_psf(raster, grid, npix, scale_deg, distance=None, options=None):
    import jax.numpy as jnp

    from invglare.optics.propagator import make_propagator

    prop = make_propagator(
        window_mm=float(grid.width_mm),
        focal_length_mm=distance or 17.0,
        fft_wavelength_nm=LAM,
        shortest_wavelength_nm=LAM,
        npix=npix,
        pixel_scale_deg=scale_deg,
        aperture_npix=grid.npix,
        propagation="fraunhofer" if distance is None else "fresnel",
        method="quad",
        method_options=options,
    )
    field = jnp.asarray(raster, jnp.float32)
    prop = prop.prepared(field)
    return np.asarray(prop(field, LAM), np.float64), prop


def _metrics(ref: np.ndarray, new: np.ndarray) -> dict[str, float]:
    """SSIM of the six-decade log images and linear PSNR over the reference peak (the
    definitions of invglare.regress.compare)."""
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    peak = float(ref.max())

    def log(x):
        return np.clip(1.0 + np.log10(np.maximum(x / peak, 1e-12)) / DECADES, 0.0, 1.0)

    return {
        "ssim_log": float(structural_similarity(log(ref), log(new), data_range=1.0)),
        "psnr_db": float(peak_signal_noise_ratio(ref, new, data_range=peak)),
        "max_err": float(np.max(np.abs(new - ref)) / peak),
    }


def fig8(n: int = 128) -> tuple[dict, np.ndarray]:
    """Fig. 8: quad far and near fields (culling + symmetry) against 8x padded discrete
    references for the four apertures; metrics and a grid image (rows: apertures;
    columns: aperture, far quad, far reference, near quad, near reference)."""
    import jax.numpy as jnp

    from invglare.optics.fraunhofer import intensity_fft
    from invglare.optics.fresnel import angular_spectrum

    rows, metrics = [], {}
    for name in PAPER_APERTURES:
        raster, grid = paper_raster(name, n), paper_grid(n)
        m = 8 * n
        far_ref = np.asarray(intensity_fft(jnp.asarray(raster), m, m // 4), np.float64)
        scale = math.degrees(LAM * 1e-6 / (m * float(grid.pitch_mm)))
        far, _ = _quad_psf(raster, grid, m // 4, scale, options={"cull_below": CULL})
        d = near_distance_mm()
        u = angular_spectrum(jnp.asarray(raster, jnp.complex64), grid, LAM, d, pad_npix=8 * n,
                             kind="fresnel")  # fmt: skip
        # Per unit power through the aperture (sum |t|), as every PSF.
        near_ref = np.abs(np.asarray(u)) ** 2 / np.sum(np.abs(raster))
        near, _ = _quad_psf(raster, grid, n, math.degrees(float(grid.pitch_mm) / d), d,
                            {"cull_below": CULL})  # fmt: skip
        metrics[name] = {"far": _metrics(far_ref, far), "near": _metrics(near_ref, near)}
        rows.append(
            _strip(
                [
                    _magnified(_grey(raster), m // 4 // n),
                    _log_image(far),
                    _log_image(far_ref),
                    _magnified(_log_image(near, near_ref.max(), NEAR_DECADES), m // 4 // n),
                    _magnified(_log_image(near_ref, None, NEAR_DECADES), m // 4 // n),
                ]
            )
        )
    grid_image = np.concatenate(
        [np.concatenate([r, np.ones((4, r.shape[1], 3))]) for r in rows], axis=0
    )
    return metrics, grid_image


def culling_table(n: int = 1024) -> dict[str, dict[str, float]]:
    """Share of the output kept and what culling (below 1e-7 of the peak) lost."""
    import jax.numpy as jnp

    from invglare.optics.quad import quad_far_field
    from invglare.optics.quad.cull import culling_error, kept_fraction
    from invglare.optics.quad.prepare import as_tiles

    out = {}
    for name in PAPER_APERTURES:
        raster, grid = paper_raster(name, n // 2), paper_grid(n // 2)
        culled, prop = _quad_psf(raster, grid, n, None, options={"cull_below": CULL})
        full = np.asarray(
            quad_far_field(prop.plan, jnp.asarray(raster, jnp.float32), 1.0 / n, n), np.float64
        )
        out[name] = {
            "kept": kept_fraction(as_tiles(prop.tiles), n),
            "mirrors": f"{'x' if prop.plan.mirror_x else ''}{'y' if prop.plan.mirror_y else ''}"
            or "none",
            **culling_error(full, culled),
        }
    return out


def progressive_figure_and_errors(n: int = 256) -> tuple[dict, np.ndarray]:
    """60 frames of the moving shadow per aperture: the worst error of the progressive
    image against a full evaluation (checked every frame), the mean quads per update and
    per full frame; and fig. 3: a frame with its difference quads (green: disoccluded,
    red: newly occluded)."""
    from invglare._core.grids import AngularGrid
    from invglare.optics.quad.progressive import ProgressiveQuads, quads_of

    out, panels = {}, []
    for name in PAPER_APERTURES:
        frame, grid = shadow_frames(name, n)
        outgrid = AngularGrid(2 * n, math.degrees(LAM * 1e-6 / (2 * n * float(grid.pitch_mm))))
        prog = ProgressiveQuads(grid, outgrid, LAM)
        worst = 0.0
        full_quads = []
        for t in range(60):
            psf = prog.psf(frame(t))
            ref = prog.full_psf(frame(t))
            full_quads.append(prog.last_full.quads)
            worst = max(worst, float(np.max(np.abs(psf - ref)) / ref.max()))
        out[name] = {
            "worst_error": worst,
            "update_quads": float(np.mean([s.quads for s in prog.stats[1:]])),
            "full_quads": float(np.mean(full_quads)),
        }
        t = 12
        image = _magnified(_grey(frame(t)), 2)
        diff = frame(t) - frame(t - 1)
        green, red = (0.2, 1.0, 0.2), (1.0, 0.2, 0.2)
        for part, colour in ((np.maximum(diff, 0), green), (np.maximum(-diff, 0), red)):
            quads = quads_of(part, 0)
            if quads is not None:
                x0, y0, w, h, _ = quads
                _outline(image, y0, x0, h, w, colour, 2)
        panels.append(image)
    return out, _strip(panels)


def fit_comparison() -> dict[str, dict[str, float]]:
    """A heptagon diaphragm's rotation and diameter fitted to a noisy 64 x 64 photo made
    from the exact polygon far field of invglare.reference (not the fitted code), with
    invglare's MFT of a 64 px raster and with the polygon method: Levenberg-Marquardt on
    Poisson-weighted residuals (optimistix), float64; error of the estimates against the
    truth, their standard errors, and the time of the solve after compilation."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import optimistix as optx

    from invglare._core.grids import AngularGrid
    from invglare.aperture import Aperture, RegularPolygon
    from invglare.models.aperture_psf import AperturePSF
    from invglare.reference.closed_forms import polygon_far_field, regular_polygon_vertices

    truth = {"rotation_deg": 4.0, "diameter_mm": 3.6}
    npix, scale = 64, 0.002
    with jax.enable_x64(True):
        out = AngularGrid(npix, scale)
        theta = np.asarray(out.coords_rad())
        verts = regular_polygon_vertices(7, truth["diameter_mm"], truth["rotation_deg"])
        exact = np.asarray(polygon_far_field(theta[None, :], theta[:, None], verts, LAM))
        photo_mean = 2e6 * exact * float(out.solid_angle_sr())
        photo = np.random.default_rng(11).poisson(photo_mean).astype(np.float64)
        sigma = np.sqrt(np.maximum(photo, 1.0))
        results = {}
        for method in ("mft", "polygon"):
            start = RegularPolygon(7, 3.5, rotation_deg=3.0)
            model = AperturePSF.build(
                Aperture((start,)), focal_length_mm=17.0, npix=npix, pixel_scale_deg=scale,
                aperture_npix=64, window_mm=4.0, method=method,
            )  # fmt: skip

            def residuals(y, args, model=model):
                m = eqx.tree_at(
                    lambda m: (m.aperture.shapes[0].rotation_deg, m.aperture.shapes[0].diameter_mm),
                    model,
                    (y[0], y[1]),
                )
                return ((y[2] * m() - photo) / sigma).reshape(-1)

            def fit(y0, residuals=residuals):
                sol = optx.least_squares(
                    residuals,
                    optx.LevenbergMarquardt(rtol=1e-8, atol=1e-8),
                    y0,
                    max_steps=100,
                    throw=False,
                )
                # Not the whole solution: its state holds a jaxpr (the Jacobian operator),
                # which a compiled call cannot return.
                return sol.value, sol.stats["num_steps"]

            solve = jax.jit(fit)
            y0 = jnp.asarray([3.0, 3.5, 1.9e6])
            jax.block_until_ready(solve(y0))
            t0 = time.perf_counter()
            y, n_steps = jax.block_until_ready(solve(y0))
            y = np.asarray(y)
            seconds = time.perf_counter() - t0
            jac = np.asarray(jax.jacfwd(lambda v: residuals(v, None))(jnp.asarray(y)))
            cov = np.linalg.inv(jac.T @ jac)
            chi2 = float(np.sum(np.asarray(residuals(jnp.asarray(y), None)) ** 2))
            results[method] = {
                "rotation_error_deg": float(y[0] - truth["rotation_deg"]),
                "rotation_se_deg": float(np.sqrt(cov[0, 0])),
                "diameter_error_mm": float(y[1] - truth["diameter_mm"]),
                "diameter_se_mm": float(np.sqrt(cov[1, 1])),
                "chi2_per_pixel": chi2 / photo.size,
                "steps": int(n_steps),
                "solve_s": seconds,
            }
    return results


# ------------------------------------------------------------------------------ report


def _goals(records: list[dict]) -> list[str]:
    by_key = {(r["case"], r["size"]): r for r in records}

    def ms(case, n):
        r = by_key.get((case, n))
        return None if r is None else r["median_ms"]

    lines = []
    for name in ("circle", "heptagon"):
        r = by_key.get((f"quad_far_{name}", 1024))
        if r:
            verdict = "met" if r["ratio"] <= 2.0 else "not met"
            lines.append(
                f"- far field of the {name} with culling and symmetry at 1024²: "
                f"{r['ratio']:.2f}x the FFT floor ({r['median_ms']:.1f} ms, floor "
                f"{r['floor_ms']:.1f} ms): goal <= 2x **{verdict}**"
            )
    for name in PAPER_APERTURES:
        speed = {
            n: ms(f"quad_prog_full_{name}", n) / ms(f"quad_prog_{name}", n)
            for n in (256, 512, 1024, 2048)
            if ms(f"quad_prog_{name}", n) and ms(f"quad_prog_full_{name}", n)
        }
        if speed:
            short = [f"{n}²" for n, s in speed.items() if s < 3.0]
            verdict = "not met" if short else "met"
            lines.append(
                f"- progressive vs full per frame, {name}: "
                + ", ".join(f"{s:.1f}x" for s in speed.values())
                + f" (256-2048): goal >= 3x **{verdict}**"
                + (f" (below 3x at {', '.join(short)})" if short else "")
            )
    padded = ms("quad_near_padded", 1024)
    for name in PAPER_APERTURES:
        near = ms(f"quad_near_{name}", 1024)
        if padded and near:
            speed = padded / near
            verdict = "met" if speed >= 30 else "not met"
            lines.append(
                f"- near field of the {name} at 1024² vs the 8x padded angular spectrum: "
                f"{speed:.0f}x faster: goal >= 30x **{verdict}**"
            )
    return lines


def far_and_near(name: str, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The aperture's quad far field (2n² output at the FFT's own pixel, no padding) and
    near field (n² on the raster's own grid at Fresnel number 10) from an n² raster."""
    grid, raster = paper_grid(n), paper_raster(name, n)
    far, _ = _quad_psf(raster, grid, 2 * n, None)
    d = near_distance_mm()
    near, _ = _quad_psf(raster, grid, n, math.degrees(float(grid.pitch_mm) / d), d)
    return far, near


def readme_figure(n: int = 64) -> np.ndarray:
    """The README's figure: the heptagon's quadtree (fig. 1a) from an n² raster, its far
    field (log, six decades) and near field (log, two decades), side by side."""
    from invglare.optics.quad import build_quadtree

    raster = paper_raster("heptagon", n)
    far, near = far_and_near("heptagon", n)
    scale = max(1, 128 // n)
    return _strip(
        [quadtree_figure(raster, build_quadtree(raster), 2 * scale),
         _magnified(_log_image(far), scale), _magnified(_log_image(near, None, NEAR_DECADES),
                                                        2 * scale)]
    )  # fmt: skip


def write_report(out_dir: Path, quick: bool = False) -> Path:
    """Measure, draw and write ``report.md`` in `out_dir` (next to the bench's files)."""
    from invglare.files.atomic import write_json_atomic, write_text_atomic
    from invglare.files.images import write_png
    from invglare.optics.quad import build_quadtree

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    sizes = (256, 512) if quick else PAPER_SIZES
    counts = table1_counts(sizes)
    raster = paper_raster("heptagon", 128)
    write_png(out_dir / "quadtree_heptagon.png", quadtree_figure(raster, build_quadtree(raster)))
    half = raster.reshape(64, 2, 64, 2).mean(axis=(1, 3))
    binary = (half >= 0.5).astype(float)
    write_png(
        out_dir / "quadtree_heptagon_binary_half.png",
        quadtree_figure(binary, build_quadtree(binary, band=None), 8),
    )
    far, near = far_and_near("heptagon", 256)
    write_png(out_dir / "far_heptagon.png", _log_image(far))
    write_png(out_dir / "near_heptagon.png", _magnified(_log_image(near, None, NEAR_DECADES), 2))
    write_png(out_dir / "readme_quad.png", readme_figure(128))
    metrics, fig8_image = fig8(64 if quick else 128)
    write_png(out_dir / "fig8_grid.png", fig8_image)
    culling = culling_table(256 if quick else 1024)
    progressive, fig3_image = progressive_figure_and_errors(64 if quick else 256)
    write_png(out_dir / "fig3_difference_quads.png", fig3_image)
    fits = fit_comparison()
    measured = {"table1": counts, "fig8": metrics, "culling": culling,
                "progressive": progressive, "fit": fits}  # fmt: skip
    write_json_atomic(out_dir / "measured.json", measured)
    bench_path = out_dir / "bench.json"
    records = json.loads(bench_path.read_text())["records"] if bench_path.is_file() else []
    meta = json.loads(bench_path.read_text())["meta"] if bench_path.is_file() else {}
    text = render(measured, records, meta, sizes)
    return write_text_atomic(out_dir / "report.md", text)


def render(measured: dict, records: list[dict], meta: dict, sizes) -> str:
    counts = measured["table1"]
    lines = [
        "# Quad-based Fourier transform: invglare beside Scandolo, Lee & Eisemann (2018)",
        "",
        "Measured by `python -m invglare.bench.quad_report` (quality, counts, fits) and "
        "`invglare bench quad --sizes 256,512,1024,2048 --skip fit --skip sample --out-dir "
        "reports/quad` (timings: [bench.md](bench.md)). "
        + (
            f"Timings of {meta.get('date')}, load average {meta.get('load_1m_start')} to "
            f"{meta.get('load_1m_end')} on 2 shared cores. {cpu_line(meta.get('cpu'))} Ratios "
            "to the FFT floor differ between CPUs."
            if meta
            else "No timings yet."
        ),
        "",
        "The paper's figures are images we cannot reproduce here; its tables are quoted "
        "beside ours, and our figures are drawn from the same experiments.",
        "",
        "## The quadtree (fig. 1a, 2)",
        "",
        "![quadtree](quadtree_heptagon.png) ![binary half size](quadtree_heptagon_binary_half.png)",
        "",
        "Left: the heptagon's soft 128² raster from pixels (white squares, cyan 2:1 quads, red "
        "negative quads; every fractional edge pixel is its own quad). Right: the paper's "
        "input, a binary raster from the half-size start.",
        "",
        "### Table 1: quads",
        "",
        "| aperture | N | paper | soft, from pixels (exact) | soft, half size "
        "| binary, half size |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for name in PAPER_APERTURES:
        for n in sizes:
            c = counts[name][n]
            paper = PAPER_TABLE1[name][PAPER_SIZES.index(n)]
            lines.append(
                f"| {name} | {n} | {paper} | {c['soft']} | {c['soft_half']} | {c['binary_half']} |"
            )
    lines += [
        "",
        "Soft rasters cost one quad per fractional edge pixel (exact transforms, exact "
        "gradients at the edges); the binary half-size rasters, the paper's kind of input, "
        "are of the paper's order (its exact shapes and sizes are not given).",
        "",
        "## Far and near field (fig. 1c, 1d, 8)",
        "",
        "![far](far_heptagon.png) ![near](near_heptagon.png)",
        "",
        "The heptagon (256² raster): far field on a 512² output at the FFT's own pixel, near "
        "field on the raster's own grid at Fresnel number 10; log10 over six decades (far) "
        "and two (near).",
        "",
        "![fig 8](fig8_grid.png)",
        "",
        "Columns: aperture, far field (quads with culling and symmetry), its 8x padded FFT, "
        "near field (quads), its 8x padded angular spectrum. The paper's fig. 8 gives "
        "SSIM/PSNR against discrete references; ours (SSIM of six-decade log images, linear "
        "PSNR over the reference's peak):",
        "",
        "| aperture | far SSIM | far PSNR dB | near SSIM | near PSNR dB |",
        "|---|---:|---:|---:|---:|",
    ]
    for name, m in measured["fig8"].items():
        lines.append(
            f"| {name} | {m['far']['ssim_log']:.4f} | {m['far']['psnr_db']:.1f} | "
            f"{m['near']['ssim_log']:.4f} | {m['near']['psnr_db']:.1f} |"
        )
    lines += [
        "",
        "## Culling and symmetry (sec. 4.3, Table 2)",
        "",
        f"Culling below {CULL:g} of the peak (coarse pass at 1/8 resolution with analytic "
        "derivatives, neighbours kept), mirrors detected on the raster:",
        "",
        "| aperture | mirrors | output kept | max error / peak | energy lost |",
        "|---|---|---:|---:|---:|",
    ]
    for name, c in measured["culling"].items():
        lines.append(
            f"| {name} | {c['mirrors']} | {c['kept']:.2f} | {c['max_error_over_peak']:.2g} | "
            f"{c['lost_energy']:.2g} |"
        )
    lines += _table_rows(records)
    lines += [
        "",
        "## Progressive refinement (fig. 3)",
        "",
        "![fig 3](fig3_difference_quads.png)",
        "",
        "A frame of the moving shadow with the quadtrees of its difference, as the paper "
        "builds them (green: light disoccluded, red: newly occluded). invglare evaluates a "
        "difference of at most "
        f"{PIXEL_QUADS_UP_TO} non-zero pixels pixel by pixel instead, one 1x1 quad each, "
        "summed into a dense matrix of the crop's rows and columns (the two quadtrees "
        "cost more than they saved, and their quads of many sizes have more distinct "
        "intervals than the crop has rows: "
        "`invglare.optics.quad.progressive.difference_quads`), so the quads per update "
        "below are pixels. Over 60 frames (256² raster, 512² output, float32):",
        "",
        "| aperture | worst error / peak | quads per update | quads per full frame |",
        "|---|---:|---:|---:|",
    ]
    for name, p in measured["progressive"].items():
        lines.append(
            f"| {name} | {p['worst_error']:.2g} | {p['update_quads']:.0f} | {p['full_quads']:.0f} |"
        )
    fits = measured["fit"]
    lines += [
        "",
        "## In a fit: the polygon method against the MFT",
        "",
        "A heptagon's rotation and diameter (and the flux) fitted to a 64² Poisson photo made "
        "from `invglare.reference.closed_forms.polygon_far_field` (truth 4°, 3.6 mm), "
        "Levenberg-Marquardt, float64:",
        "",
        "| method | rotation error | ± | diameter error mm | ± | chi²/pixel | steps | solve s |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for method, f in fits.items():
        lines.append(
            f"| {method} | {f['rotation_error_deg']:.2g}° | {f['rotation_se_deg']:.2g} | "
            f"{f['diameter_error_mm']:.2g} | {f['diameter_se_mm']:.2g} | "
            f"{f['chi2_per_pixel']:.3f} | {f['steps']} | {f['solve_s']:.2f} |"
        )
    lines += ["", "## Goals", "", *(_goals(records) or ["- no timings in bench.json yet"]), ""]
    return "\n".join(lines)


def _table_rows(records: list[dict]) -> list[str]:
    """Tables 2-4 beside the paper's, from the bench records."""
    by_key = {(r["case"], r["size"]): r["median_ms"] for r in records}
    out = []
    for title, table, cases in (
        ("Table 2 (heptagon far field)", PAPER_TABLE2,
         {"none": "quad_table2_none", "cull": "quad_table2_cull", "sym": "quad_table2_sym",
          "both": "quad_far_heptagon"}),
        ("Table 3 (60 wavelengths)", PAPER_TABLE3,
         {"full": "quad_spectral_full", "batch": "quad_spectral_batch"}),
        ("Table 4 (near field)", PAPER_TABLE4,
         {"padded": "quad_near_padded", **{a: f"quad_near_{a}" for a in PAPER_APERTURES}}),
    ):  # fmt: skip
        rows = []
        for key, case in cases.items():
            cells = []
            for i, n in enumerate(PAPER_SIZES[:4]):
                here = by_key.get((case, n))
                paper = table[key][i]
                cells.append(
                    f"{'-' if paper is None else paper} / {'-' if here is None else f'{here:.1f}'}"
                )
            rows.append(f"| {key} | " + " | ".join(cells) + " |")
        out += [
            "",
            f"### {title}: paper ms (GTX 1080 Ti) / ms here (2 CPU cores)",
            "",
            "| variant | 256² | 512² | 1024² | 2048² |",
            "|---|---:|---:|---:|---:|",
            *rows,
        ]
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out-dir", default="runs/quad")
    parser.add_argument("--quick", action="store_true", help="small sizes (a smoke run)")
    parser.add_argument(
        "--figure", metavar="PNG", help="write only the README's figure (docs/images/quad.png)"
    )
    args = parser.parse_args(argv)
    if args.figure:
        from invglare.files.images import write_png

        print(write_png(Path(args.figure), readme_figure()))
        return
    print(write_report(Path(args.out_dir), quick=args.quick))


if __name__ == "__main__":
    main()
