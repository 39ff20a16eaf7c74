"""Figures of a batch fit's population: each parameter's histogram, fitted against true.

- ``histograms.png``: one panel per fitted parameter, the histogram of the photos' fitted
  values (and of the true values, as a line, where the truth is known);
- ``fitted_vs_true.png`` (only when some truth is known): one panel per parameter with a
  truth, each photo's fitted value with its standard error against the true value, and
  the diagonal.

Photos without a result (failed) are left out. Written atomically, in the batch folder.

**Example:** ``population_figures(Path("reports/eye_population/batch"), rows)``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from invglare.files.atomic import atomic_path
from invglare.fit.batch_table import PhotoRow, parameter_paths, short_names
from invglare.fit.report import unit_of


def population_figures(folder: Path, rows: Sequence[PhotoRow]) -> list[str]:
    """Write the population figures into `folder`. **Returns:** their file names."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fitted = [r for r in rows if r.result is not None]
    paths = parameter_paths(fitted)
    if not paths:
        return []
    names = short_names(paths)

    def label(p: str) -> str:
        unit = unit_of(p)
        return names[p] + (f" ({unit})" if unit else "")

    def truth_of(r: PhotoRow, p: str) -> float | None:
        t = r.result.truth.get(p) if r.result.truth else None
        return None if t is None or not math.isfinite(t) else float(t)

    files = []
    n = len(paths)
    cols = min(n, 4)
    nrows = math.ceil(n / cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(3.6 * cols, 2.9 * nrows),
                             constrained_layout=True, squeeze=False)  # fmt: skip
    for ax, p in zip(axes.flat, paths, strict=False):
        values = np.array([r.result.values[p] for r in fitted if p in r.result.values])
        truths = np.array([t for r in fitted if (t := truth_of(r, p)) is not None])
        both = np.concatenate([values, truths])
        both = both[np.isfinite(both)]
        bins = np.histogram_bin_edges(both, bins=min(20, max(5, len(values)))) if both.size else 10
        ax.hist(values[np.isfinite(values)], bins=bins, color="tab:blue", alpha=0.7,
                label="fitted")  # fmt: skip
        if truths.size:
            ax.hist(truths, bins=bins, histtype="step", color="black", lw=1.2, label="true")
        ax.set_xlabel(label(p))
        ax.set_ylabel("photos")
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=7)
    fig.suptitle(f"fitted parameters of {len(fitted)} photos")
    _save(fig, Path(folder) / "histograms.png", plt)
    files.append("histograms.png")

    known = [p for p in paths if any(truth_of(r, p) is not None for r in fitted)]
    if known:
        cols = min(len(known), 4)
        nrows = math.ceil(len(known) / cols)
        fig, axes = plt.subplots(nrows, cols, figsize=(3.6 * cols, 3.4 * nrows),
                                 constrained_layout=True, squeeze=False)  # fmt: skip
        for ax, p in zip(axes.flat, known, strict=False):
            pts = [(t, r.result.values[p], r.result.stderr[p]) for r in fitted
                   if (t := truth_of(r, p)) is not None]  # fmt: skip
            t, v, s = (np.array(c, dtype=float) for c in zip(*pts, strict=True))
            ax.errorbar(t, v, yerr=np.where(np.isfinite(s), s, 0.0), fmt="o", ms=3,
                        color="tab:blue", ecolor="grey", lw=0.8)  # fmt: skip
            lo, hi = float(np.nanmin([t.min(), v.min()])), float(np.nanmax([t.max(), v.max()]))
            pad = 0.05 * (hi - lo or abs(hi) or 1.0)
            ax.plot([lo - pad, hi + pad], [lo - pad, hi + pad], "k--", lw=0.8)
            ax.set_xlabel(f"true {label(p)}")
            ax.set_ylabel("fitted")
        for ax in list(axes.flat)[len(known):]:
            ax.axis("off")
        fig.suptitle("fitted (± standard error) against true")
        _save(fig, Path(folder) / "fitted_vs_true.png", plt)
        files.append("fitted_vs_true.png")
    return files


def _save(fig, path: Path, plt) -> None:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)
