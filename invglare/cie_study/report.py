"""Reports of the CIE study: ``reports/cie/`` for several ages, one folder per reference fit.

**Example:**

```python
write_cie_report([fit_cie(25.0, 0.5), fit_cie(70.0, 0.5)], "runs")   # runs/cie/cie.md
write_gsf_report(result, "reports/cie_A50_p1", reference="the CIE GSF, age 50")
```
"""

from __future__ import annotations

import datetime as dt
import math
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from invglare.cie_study.fit import CieFitResult
from invglare.errors import ConfigError
from invglare.files.outputs import RUNS_DIR

__all__ = ["write_cie_report", "write_gsf_report"]


def _slug(result: CieFitResult) -> str:
    return f"cie_A{result.age:g}_p{result.pigmentation:g}".replace(".", "_")


def _short(path: str) -> str:
    return (
        path.replace("aperture.particles[0]", "cornea")
        .replace("aperture.particles[1]", "lens")
        .replace(".radius_mean_mm", " radius (mm)")
        .replace(".count", " count")
    )


def _figure(results: Sequence[CieFitResult], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import jax
    import matplotlib.pyplot as plt

    from invglare.files.atomic import atomic_path
    from invglare.reference.cie import cie_gsf

    fig, (ax, axr) = plt.subplots(
        2, 1, figsize=(7, 7), sharex=True, gridspec_kw={"height_ratios": [3, 1]},
        constrained_layout=True,
    )  # fmt: skip
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    wide = np.geomspace(0.1, 100.0, 300)
    for k, res in enumerate(results):
        c = colours[k % len(colours)]
        if res.age is None:  # a reference that is not the CIE's: its annulus means
            name = res.label
            ax.loglog(res.theta_deg, res.target_gsf, "s", color=c, ms=4, mfc="none",
                      label=f"reference {name}")  # fmt: skip
        else:
            with jax.enable_x64(True):
                curve = np.asarray(cie_gsf(wide, res.age, res.pigmentation))
            name = f"A={res.age:g}, p={res.pigmentation:g}"
            ax.loglog(wide, curve, color=c, lw=1, alpha=0.5, label=f"CIE {name}")
        ax.loglog(res.theta_deg, res.model_gsf, "o-", color=c, ms=3, label=f"eye model {name}")
        axr.semilogx(res.theta_deg, res.residual_log10, "o-", color=c, ms=3)
    lo, hi = results[0].theta_deg[0], results[0].theta_deg[-1]
    for a in (ax, axr):
        a.axvspan(lo, hi, color="0.9", zorder=0)
    ax.set_ylabel("GSF (sr$^{-1}$)")
    ax.set_title(title)
    ax.legend(fontsize=7)
    axr.axhline(0.0, color="0.3", lw=0.8)
    cie = all(r.age is not None for r in results)
    axr.set_ylabel("log10(model / CIE)" if cie else "log10(model / reference)")
    axr.set_xlabel("angle from the source (deg)")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)


def write_cie_report(
    results: Sequence[CieFitResult], out_dir: str | os.PathLike[str] = RUNS_DIR
) -> Path:
    """Write ``<out_dir>/cie/cie.md``, a log-log figure per fit, one of all, and ``fits.json``.

    **Returns:** the markdown path. Files are written atomically.
    """
    from invglare.files.atomic import write_json_atomic, write_text_atomic

    if not results or any(r.age is None for r in results):
        raise ConfigError("write_cie_report needs CIE fits (from fit_cie)")
    folder = Path(out_dir) / "cie"
    for r in results:
        _figure([r], folder / f"{_slug(r)}.png", r.label)
    if len(results) > 1:
        _figure(results, folder / "cie_all.png", "eye model vs CIE glare spread function")
    setup = results[0].setup
    stamp = dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    paths = list(results[0].values)
    lines = [
        "# The eye model fitted to the CIE glare spread function",
        "",
        f"`invglare regress --cie`, {stamp}. Model: a {setup.pupil_diameter_mm:g} mm pupil at "
        f"{min(setup.wavelengths_nm):g}-{max(setup.wavelengths_nm):g} nm "
        f"({len(setup.wavelengths_nm)} wavelengths, V(λ)-weighted) with "
        f"{len(setup.populations)} particle populations "
        f"({', '.join(p.region for p in setup.populations)}), {setup.aperture_npix} pupil "
        f"samples, {setup.npix}² output pixels of {setup.pixel_scale_deg:g}° (MFT). Fitted "
        f"range {setup.theta_min_deg:g}°–{setup.max_angle_deg():.3g}° in {setup.n_bins} "
        f"logarithmic annuli: the model's raster is alias-free to "
        f"{setup.alias_free_deg():.3g}° and the fit stops at 0.9 of that. Residuals are "
        "`log10(model / CIE)` per annulus; Levenberg–Marquardt from "
        f"{setup.n_starts} start(s).",
        "",
        "| age | p | rms log10 | max log10 | CIE light beyond the range | "
        + " | ".join(_short(p) for p in paths)
        + " | pupil light blocked | converged | time s |",
        "|---|---|---|---|---|" + "---|" * len(paths) + "---|---|---|",
    ]
    for r in results:
        beyond = "–" if r.energy_beyond is None else f"{100 * r.energy_beyond:.1f} %"
        vals = " | ".join(f"{r.values[p]:.4g}" for p in paths)
        lines.append(
            f"| {r.age:g} | {r.pigmentation:g} | {r.rms_log10:.3f} | {r.max_log10:.3f} | "
            f"{beyond} | {vals} | {100 * r.blocked_fraction:.0f} % | "
            f"{'yes' if r.converged else 'no'} | {r.seconds:.0f} |"
        )
    lines += [""]
    for r in results:
        lines.append(f"![{r.label}](cie/{_slug(r)}.png)".replace("cie/cie/", "cie/"))
    if len(results) > 1:
        lines += ["", "![all fits](cie_all.png)"]
        moved = _what_moved(results, paths)
        if moved:
            lines += ["", "## What moved", "", moved]
    lines += [
        "",
        "## Reading it",
        "",
        "A residual of 0.1 log10 units is a factor 1.26. The CIE light beyond the range is the",
        "share of its glare within 100° that lies outside what the model's sampling covers; the",
        "fit says nothing about it. The residuals wiggle by a few hundredths from annulus to",
        "annulus: that is the speckle of one random draw of particles, not noise in the CIE.",
        "The particle counts and radii are effective values of this diffraction model (opaque",
        "particles in one plane), not counts of cells; the share of the pupil's light they",
        "block shows what it takes opaque obstacles to reach the CIE's level near 0.1°, where",
        "the CIE's terms stand for the eye's optical blur rather than for scattering. See",
        "`invglare/cie_study/fit.py` for the reasoning and the limits.",
        "",
    ]
    # Figures sit next to the markdown, so links are relative to the cie/ folder.
    text = "\n".join(lines).replace("](cie/", "](")
    write_json_atomic(folder / "fits.json", [r.to_dict() for r in results])
    path = folder / "cie.md"
    write_text_atomic(path, text)
    return path


def write_gsf_report(
    result: CieFitResult,
    folder: str | os.PathLike[str],
    *,
    reference: str,
    config_path: str | os.PathLike[str] | None = None,
) -> Path:
    """Write one reference fit's report folder: ``report.md``, ``gsf.png``, ``fit.json``.

    The folder is replaced as a whole once complete (an interrupted run leaves the
    previous report). `reference` says in words what was fitted (the CIE's age and
    pigmentation, or the file). **Returns:** the folder.
    """
    from invglare.files.atomic import atomic_directory, dumps_json

    setup = result.setup
    beyond = (
        ""
        if result.energy_beyond is None
        else f" The CIE puts {100 * result.energy_beyond:.1f} % of its light within 100° "
        "beyond the fitted range, which this fit says nothing about."
    )
    lines = [
        f"# Reference fit: {result.label}",
        "",
        f"- **Reference:** {reference}",
        f"- **Config:** `{config_path}`" if config_path else None,
        f"- **Model:** a {setup.pupil_diameter_mm:g} mm pupil at {min(setup.wavelengths_nm):g}-"
        f"{max(setup.wavelengths_nm):g} nm ({len(setup.wavelengths_nm)} wavelengths, "
        f"V(λ)-weighted), particle populations {', '.join(p.region for p in setup.populations)}"
        f", {setup.aperture_npix} pupil samples, {setup.npix}² output pixels of "
        f"{setup.pixel_scale_deg:g}° (MFT), seed {setup.seed}",
        f"- **Fitted:** the radially averaged GSF in {setup.n_bins} logarithmic annuli over "
        f"{setup.theta_min_deg:g}°–{setup.max_angle_deg():.3g}° (the raster is alias-free to "
        f"{setup.alias_free_deg():.3g}°), residuals `log10(model / reference)`; "
        f"Levenberg–Marquardt from {len(result.starts)} start(s)",
        "",
        "## Result",
        "",
        f"Residual **{result.rms_log10:.3f}** log10 units rms, {result.max_log10:.3f} at worst "
        f"(a factor {10**result.rms_log10:.3f} and {10**result.max_log10:.3f}); "
        f"{'converged' if result.converged else 'stopped at max_steps'} after "
        f"{result.n_steps} steps; {result.seconds:.0f} s. The fitted particles block "
        f"{100 * result.blocked_fraction:.0f} % of the pupil's light.{beyond}",
        "",
        "| parameter | value |",
        "|---|---:|",
        *(f"| `{p}` ({_short(p)}) | {v:.5g} |" for p, v in result.values.items()),
        "",
        "| angle (deg) | reference (sr⁻¹) | model (sr⁻¹) | log10(model / reference) |",
        "|---:|---:|---:|---:|",
        *(
            f"| {t:.3g} | {a:.4g} | {m:.4g} | {r:+.3f} |"
            for t, a, m, r in zip(
                result.theta_deg,
                result.target_gsf,
                result.model_gsf,
                result.residual_log10,
                strict=True,
            )
        ),
        "",
        "![GSF](gsf.png)",
        "",
        "The particle counts and radii are effective values of this diffraction model (opaque",
        "particles in one plane), not counts of cells; see `invglare/cie_study/fit.py`.",
        "",
    ]
    with atomic_directory(folder) as tmp:
        _figure([result], tmp / "gsf.png", result.label)
        (tmp / "report.md").write_text("\n".join(x for x in lines if x is not None), "utf-8")
        (tmp / "fit.json").write_text(dumps_json(result.to_dict()), "utf-8")
    return Path(folder)


def _what_moved(results: Sequence[CieFitResult], paths: list[str]) -> str:
    """One sentence per pigmentation: how each parameter changed from the youngest age."""
    sentences = []
    for pig in sorted({r.pigmentation for r in results}):
        group = sorted((r for r in results if r.pigmentation == pig), key=lambda r: r.age)
        if len(group) < 2:
            continue
        ages = " → ".join(f"{r.age:g}" for r in group)
        parts = []
        for p in paths:
            trail = " → ".join(f"{r.values[p]:.3g}" for r in group)
            ratio = group[-1].values[p] / group[0].values[p] if group[0].values[p] else math.inf
            parts.append(f"{_short(p)} {trail} (×{ratio:.2f})")
        sentences.append(f"With age ({ages}, p = {pig:g}): " + "; ".join(parts) + ".")
    for age in sorted({r.age for r in results}):
        group = sorted((r for r in results if r.age == age), key=lambda r: r.pigmentation)
        if len(group) < 2:
            continue
        pigs = " → ".join(f"{r.pigmentation:g}" for r in group)
        parts = [f"{_short(p)} " + " → ".join(f"{r.values[p]:.3g}" for r in group) for p in paths]
        sentences.append(f"With pigmentation ({pigs}, age {age:g}): " + "; ".join(parts) + ".")
    return "\n\n".join(sentences)
