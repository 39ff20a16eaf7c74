"""The suite's report: ``regression.md`` with a row per case and a difference image each.

**Example:**

```python
write_report(run_suite(golden_dir="tests/golden"), "runs")   # runs/regression.md
```
"""

from __future__ import annotations

import datetime as dt
import os
import platform
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from invglare._core.colour import rec709_luminance_np
from invglare.files.outputs import RUNS_DIR
from invglare.regress.cases import CASES
from invglare.regress.compare import log_scaled, metric_cells
from invglare.regress.run import CaseResult

__all__ = ["DIFF_FLOOR_LOG10", "write_report"]


def _display(image: np.ndarray) -> np.ndarray:
    """Luminance of an RGB PSF (what the figures show); a mono PSF as it is."""
    return rec709_luminance_np(image) if image.ndim == 3 else image


#: Difference images: log10 |new − golden| / peak is shown from this floor up.
DIFF_FLOOR_LOG10 = -12.0


def _figure(result: CaseResult, path: Path) -> None:
    """Write ``[golden | recomputed | difference]`` as one PNG, 2x magnified, no axes.

    Golden and recomputed: ``log10(PSF / peak)`` from -6 to 0 (magma; luminance of an
    RGB PSF). Difference: ``log10(|new − golden| / peak)`` from -12 to 0 (viridis). Plain
    images rather than a plotted figure: matplotlib's axes cost seconds per case.
    """
    from matplotlib import colormaps

    from invglare.files.images import write_png

    new = _display(np.asarray(result.psf, dtype=np.float64))
    ref = None if result.reference is None else _display(np.asarray(result.reference, np.float64))
    peak = float(np.max(ref if ref is not None else new))
    blank = np.full((*new.shape, 3), 0.5)
    magma, viridis = colormaps["magma"], colormaps["viridis"]

    def shade(img):
        return magma(log_scaled(img, peak))[..., :3]

    panels = [blank if ref is None else shade(ref), shade(new), blank]
    if ref is not None and ref.shape == new.shape:
        err = np.log10(np.maximum(np.abs(new - ref) / peak, 10.0**DIFF_FLOOR_LOG10))
        panels[2] = viridis((err - DIFF_FLOOR_LOG10) / -DIFF_FLOOR_LOG10)[..., :3]
    gap = np.ones((new.shape[0], 4, 3))
    strip = np.concatenate([panels[0], gap, panels[1], gap, panels[2]], axis=1)
    # Row 0 of a PSF is the bottom of the field (y up): flip for the image.
    strip = np.repeat(np.repeat(strip[::-1], 2, axis=0), 2, axis=1)
    write_png(path, strip)


def _environment() -> str:
    import jax

    import invglare

    version = getattr(invglare, "__version__", "unknown")
    devices = ", ".join(sorted({d.platform for d in jax.devices()}))
    return (
        f"invglare {version}, JAX {jax.__version__} on {devices}, Python "
        f"{platform.python_version()}, {platform.machine()} {platform.system()}"
    )


def write_report(
    results: Sequence[CaseResult],
    out_dir: str | os.PathLike[str] = RUNS_DIR,
    *,
    updated: Sequence[str] = (),
    golden_dir: str | os.PathLike[str] = "tests/golden",
) -> Path:
    """Write ``<out_dir>/regression.md`` and a difference figure per case (``regression/``).

    A run of some of the cases (``invglare regress CASE ...``) writes
    ``regression.partial.md`` and ``regression.partial/`` beside them instead: the report
    of the last full run stays as it was.

    **Returns:** the markdown path. Every file is written atomically.
    """
    from invglare.files.atomic import write_text_atomic

    out = Path(out_dir)
    partial = {r.case.name for r in results} != {c.name for c in CASES}
    stem = "regression.partial" if partial else "regression"
    fig_dir = out / stem
    for r in results:
        _figure(r, fig_dir / f"{r.case.name}.png")
    n_fail = sum(not r.passed for r in results)
    stamp = dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    verdict = "all cases pass" if n_fail == 0 else f"{n_fail} of {len(results)} case(s) FAIL"
    if updated:
        verdict += f" before the update; rewritten: {', '.join(updated)}"
    if partial:
        verdict += (
            f"; a partial run of {len(results)} of the {len(CASES)} cases "
            "(`regression.md` holds the last full run)"
        )
    total = sum(r.seconds for r in results)
    lines = [
        "# Golden regression",
        "",
        f"`invglare regress`, {stamp}: **{verdict}** ({len(results)} cases, "
        f"{total:.1f} s of model time). {_environment()}. Goldens: `{golden_dir}`.",
        "",
        "| case | status | rel L2 | max err / peak | SSIM (log) | PSNR dB | EE diff | time s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        cells = " | ".join(metric_cells(r.metrics))
        name = f"[{r.case.name}]({stem}/{r.case.name}.png)"
        status = r.status.upper() if r.status != "pass" else "pass"
        lines.append(f"| {name} | {status} | {cells} | {r.seconds:.1f} |")
    lines += ["", "Tolerances (a case fails when any metric is outside its bound):", ""]
    lines += [
        "| case | rel L2 ≤ | max err ≤ | SSIM ≥ | PSNR ≥ dB | EE diff ≤ | basis |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in results:
        t = r.case.tolerance
        lines.append(
            f"| {r.case.name} | {t.rel_l2:g} | {t.max_err:g} | {t.ssim_log:g} | "
            f"{t.psnr_db:g} | {t.ee_diff:g} | {t.why} |"
        )
    problems = [r for r in results if r.failures or r.config_changes]
    if problems:
        lines += ["", "## Details", ""]
        for r in problems:
            if r.failures:
                lines.append(f"- **{r.case.name}** ({r.status}): {'; '.join(r.failures)}")
            if r.config_changes:
                keys = ", ".join(r.config_changes[:8])
                more = f" and {len(r.config_changes) - 8} more" if len(r.config_changes) > 8 else ""
                lines.append(
                    f"- **{r.case.name}**: the stored header config differs from the "
                    f"registry's at {keys}{more}"
                )
    lines += [
        "",
        "## Cases",
        "",
        *[f"- `{r.case.name}`: {r.case.description}." for r in results],
        "",
        "## Metrics",
        "",
        "- rel L2: `‖new − golden‖₂ / ‖golden‖₂` over all pixels and channels;",
        "- max err / peak: `max |new − golden|` over the golden's peak;",
        "- SSIM (log): scikit-image `structural_similarity` (7×7 window, data range 1) of the",
        "  log-scaled images `clip(1 + log10(x / peak) / 6, 0, 1)` — six decades below the",
        "  golden's peak, because a PSF's glare lives far below its peak where a linear SSIM",
        "  sees nothing;",
        "- PSNR: scikit-image `peak_signal_noise_ratio` of the linear images, data range = peak",
        "  (`inf` for identical images);",
        "- EE diff: the largest difference of encircled energy (fraction of the unit-energy PSF)",
        "  at radii 1, 2, 4, … px up to the half-width, per channel.",
        "",
        f"Difference images (`{stem}/<case>.png`, click a case): left the golden, middle the",
        "recomputed PSF, as `log10(PSF / peak)` from −6 to 0 (magma; luminance for RGB, y up);",
        "right `log10(|recomputed − golden| / peak)` from −12 to 0 (viridis; all dark when the",
        "two are bit-identical).",
        "",
        "The temporal model (Ritschel et al.) is covered by one frame at a fixed time and key",
        "(`temporal_frame`).",
        "",
    ]
    path = out / f"{stem}.md"
    write_text_atomic(path, "\n".join(lines))
    return path
