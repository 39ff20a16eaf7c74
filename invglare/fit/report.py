"""Fit reports: a folder with ``report.md``, ``params.json`` and figures, written atomically.

:func:`write_report` writes everything into a hidden temporary folder beside the
destination and renames it into place only when complete (an existing report is
moved aside first and removed after), so an interrupted or failed run never
leaves a half-written report, and the previous report survives until its
successor is complete.

Contents of ``reports/NAME/``:

| file           | what                                                                  |
|----------------|-----------------------------------------------------------------------|
| `report.md`    | parameter table (value ± stderr, truth, error, units), convergence,   |
|                | reduced chi², timing (compile vs solve), the starts, discrete choices |
| `params.json`  | :meth:`invglare.fit.FitResult.to_dict` plus ``"fit"`` (inputs, wall  |
|                | time) and ``"discrete"`` (static choices and their losses)            |
| `images.png`   | target / model (log scale) and the residual in noise units            |
| `profiles.png` | radial profile and angular energy, target vs model                    |
| `loss.png`     | loss history of every start (and the loss of each discrete choice)    |

**Example:**

```python
info = ReportInfo(name="eye_daylight", target=photo, pixel_scale_deg=0.003)
write_report("reports/eye_daylight", result, info)
```
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from jaxtyping import Float

from invglare.files.atomic import atomic_directory, dumps_json
from invglare.fit.result import FitResult, _clean

_UNITS = (
    ("_mm", "mm"),
    ("_um", "µm"),
    ("_nm", "nm"),
    ("_deg", "deg"),
    ("_rad", "rad"),
    ("_px", "px"),
    ("_s", "s"),
    ("obs.flux", "counts"),
    ("obs.background", "counts/px"),
    ("obs.read_noise", "counts"),
    ("obs.gain", "e⁻/count"),
)


def unit_of(path: str) -> str:
    """The unit of a parameter from its path (``"…diameter_mm"`` → ``"mm"``; counts → ``""``)."""
    base = re.sub(r"\[[\d,\s]+\]$", "", path)  # an element of an array leaf: its leaf's unit
    for suffix, unit in _UNITS:
        if base.endswith(suffix) or base == suffix:
            return unit
    return ""


@dataclasses.dataclass
class ReportInfo:
    """What a report says besides the :class:`~invglare.fit.FitResult`.

    **Fields:**

    - `name`: the fit's name (the report's title).
    - `target`: the photo (counts, ``(h, w)``).
    - `pixel_scale_deg`: the photo's pixel scale the model was built at.
    - `saturation`: the clip level (counts) or None.
    - `config_path`, `target_path`, `model_path`, `truth_path`: the inputs, for the record.
    - `n_starts`, `solver`: settings shown in the report.
    - `wall_s`: wall time of the whole command (loading, fitting, report).
    - `discrete`: one entry per discrete choice tried, ``{"choice": {key: value},
      "loss", "reduced_chi2", "converged", "message", "timing_s"}``.
    - `discrete_truth`: ``{key: value}`` of the discrete choices in the ground truth.
    - `view_options`: options of the views (for the profile figures).
    - `sections`: model-specific results, ``{key: (title, markdown lines, JSON data)}``:
      a section of ``report.md`` after the parameters and ``params.json[key]`` (e.g. the
      ghosts of a veiling fit, :mod:`invglare.fit.ghost_report`).
    """

    name: str
    target: Float[np.ndarray, "h w"]
    pixel_scale_deg: float
    saturation: float | None = None
    config_path: Path | None = None
    target_path: Path | None = None
    model_path: Path | None = None
    truth_path: Path | None = None
    n_starts: int = 1
    solver: dict[str, Any] = dataclasses.field(default_factory=dict)
    wall_s: float | None = None
    discrete: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    discrete_truth: dict[str, int | None] = dataclasses.field(default_factory=dict)
    view_options: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict)
    sections: dict[str, tuple[str, list[str], Any]] = dataclasses.field(default_factory=dict)


# --------------------------------------------------------------------------------------
# numbers


def _fmt(x: float | None, digits: int = 5) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "—"
    return f"{x:.{digits}g}"


def _rel(path: Path | None) -> str:
    if path is None:
        return "—"
    try:
        return os.path.relpath(Path(path).resolve(), Path.cwd())
    except ValueError:  # another drive on Windows
        return str(path)


def centre_of(result: FitResult, shape: tuple[int, int]) -> tuple[float, float]:
    """The fitted source centre ``(x, y)`` in pixel index units."""
    h, w = shape
    dx = result.values.get("obs.dx_px", 0.0)
    dy = result.values.get("obs.dy_px", 0.0)
    return (w // 2 + dx, h // 2 + dy)


def profiles(result: FitResult, info: ReportInfo, background: float) -> dict[str, np.ndarray]:
    """Radial profiles and angular energy fractions of target and model (numpy)."""
    from invglare.fit.views import (
        angular_bin_angles_deg,
        angular_energy,
        radial_bin_radii,
        radial_profile,
    )

    target = np.asarray(info.target, dtype=np.float64)
    model = np.asarray(result.model_image, dtype=np.float64)
    centre = centre_of(result, target.shape)
    r_max = float(min(target.shape) // 2 - 1)
    n_rad = int(r_max)
    ang = {"n_bins": 72, "r_min": 3.0, "r_max": r_max, **info.view_options.get("angular", {})}
    out = {
        "radius_deg": radial_bin_radii(n_rad, r_max) * info.pixel_scale_deg,
        "radial_target": np.asarray(radial_profile(target, centre, n_rad, r_max)),
        "radial_model": np.asarray(radial_profile(model, centre, n_rad, r_max)),
        "angle_deg": angular_bin_angles_deg(int(ang["n_bins"])),
    }
    for key, img in (("angular_target", target), ("angular_model", model)):
        e = np.asarray(
            angular_energy(img - background, centre, int(ang["n_bins"]), ang["r_min"],
                           ang["r_max"])
        )  # fmt: skip
        out[key] = e / e.sum() if e.sum() != 0 else e
    return out


# --------------------------------------------------------------------------------------
# figures


def _figures(folder: Path, result: FitResult, info: ReportInfo) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    target = np.asarray(info.target, dtype=np.float64)
    model = np.asarray(result.model_image, dtype=np.float64)
    resid = np.asarray(result.residual_map, dtype=np.float64)
    h, w = target.shape
    s = info.pixel_scale_deg
    extent = [(-0.5 - w // 2) * s, (w - 0.5 - w // 2) * s, (h - 0.5 - h // 2) * s,
              (-0.5 - h // 2) * s]  # fmt: skip
    peak = max(float(target.max()), float(model.max()), 1e-30)
    floor = max(float(np.percentile(target, 5)), peak * 1e-6, 1e-30)
    norm = LogNorm(vmin=floor, vmax=peak)
    files = []

    fig, axes = plt.subplots(1, 3, figsize=(13.5, 4.4), constrained_layout=True)
    for ax, img, title in ((axes[0], target, "target"), (axes[1], model, "model")):
        im = ax.imshow(np.maximum(img, floor), norm=norm, cmap="inferno", extent=extent,
                       origin="upper", interpolation="nearest")  # fmt: skip
        ax.set_title(f"{title} (counts, log scale)")
        ax.set_xlabel("x (deg)")
        ax.set_ylabel("y (deg)")
    fig.colorbar(im, ax=axes[:2], shrink=0.85)
    lim = 5.0
    im = axes[2].imshow(np.clip(resid, -lim, lim), cmap="RdBu_r", vmin=-lim, vmax=lim,
                        extent=extent, origin="upper", interpolation="nearest")  # fmt: skip
    axes[2].set_title("residual (target − model) / σ")
    axes[2].set_xlabel("x (deg)")
    fig.colorbar(im, ax=axes[2], shrink=0.85)
    fig.savefig(folder / "images.png", dpi=90)
    plt.close(fig)
    files.append("images.png")

    bg = float(result.values.get("obs.background", np.median(target[:4])))
    prof = profiles(result, info, bg)
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2), constrained_layout=True)
    ax = axes[0]
    ax.semilogy(prof["radius_deg"], np.maximum(prof["radial_target"], 1e-3), ".", ms=3,
                label="target")  # fmt: skip
    ax.semilogy(prof["radius_deg"], np.maximum(prof["radial_model"], 1e-3), "-", lw=1.2,
                label="model")  # fmt: skip
    if info.saturation is not None:
        ax.axhline(info.saturation, color="grey", ls=":", lw=1, label="saturation")
    ax.set_xlabel("radius (deg)")
    ax.set_ylabel("mean counts per pixel")
    ax.set_title("radial profile")
    ax.legend()
    ax = axes[1]
    ax.plot(prof["angle_deg"], prof["angular_target"], ".-", ms=3, lw=0.6, label="target")
    ax.plot(prof["angle_deg"], prof["angular_model"], "-", lw=1.2, label="model")
    ax.set_xlabel("direction (deg, counter-clockwise from +x)")
    ax.set_ylabel("fraction of the annulus energy")
    ax.set_title("angular energy (background removed)")
    ax.set_xlim(0, 360)
    ax.legend()
    fig.savefig(folder / "profiles.png", dpi=90)
    plt.close(fig)
    files.append("profiles.png")

    n_panels = 2 if len(info.discrete) > 1 else 1
    fig, axes = plt.subplots(1, n_panels, figsize=(6 * n_panels, 4), constrained_layout=True,
                             squeeze=False)  # fmt: skip
    ax = axes[0, 0]
    offset = 0
    for k, stage in enumerate(result.stages):
        length = 0
        for i, hist in enumerate(stage.get("loss_history", [])):
            hist = [v for v in hist if v is not None and math.isfinite(v)]
            if not hist:
                continue
            x = offset + np.arange(len(hist))
            views = "+".join(stage.get("views", result.views))
            label = f"stage {k + 1} ({views}), start {stage.get('origin', list(range(99)))[i]}"
            ax.semilogy(x, hist, ".-", ms=3, lw=1, label=label)
            length = max(length, len(hist))
        offset += length
    ax.set_xlabel("accepted step")
    ax.set_ylabel("loss (sum of squared residuals)")
    ax.set_title("loss history")
    if ax.lines:
        ax.legend(fontsize=7)
    if n_panels == 2:
        ax = axes[0, 1]
        labels = [", ".join(f"{v}" for v in d["choice"].values()) for d in info.discrete]
        losses = [d["loss"] for d in info.discrete]
        ax.bar(labels, losses, color="tab:blue")
        ax.set_yscale("log")
        ax.set_xlabel(", ".join(info.discrete[0]["choice"]))
        ax.set_ylabel("best loss")
        ax.set_title("discrete choices")
    fig.savefig(folder / "loss.png", dpi=90)
    plt.close(fig)
    files.append("loss.png")
    return files


# --------------------------------------------------------------------------------------
# markdown


def _discrete_summary(info: ReportInfo) -> tuple[dict[str, Any], dict[str, Any]]:
    """The chosen discrete values and the per-key table for params.json."""
    if not info.discrete:
        return {}, {}
    best = min(info.discrete, key=lambda d: d["loss"] if math.isfinite(d["loss"]) else math.inf)
    table = {}
    for key, value in best["choice"].items():
        entry: dict[str, Any] = {"value": value}
        if info.discrete_truth.get(key) is not None:
            entry["truth"] = info.discrete_truth[key]
        entry["candidates"] = [
            {"value": d["choice"][key], "loss": d["loss"], "reduced_chi2": d.get("reduced_chi2"),
             "converged": d.get("converged")}
            for d in info.discrete
        ]  # fmt: skip
        entry["compared_by"] = dict(best.get("views") or {})
        table[key] = entry
    return best["choice"], table


def _stage_views(result: FitResult) -> str:
    """The views of each stage, e.g. ``1) radial 1, angular 1 → 2) pixels 1``."""
    seen = []
    for stage in result.stages:
        views = stage.get("views", result.views)
        if not seen or seen[-1] != views:
            seen.append(views)
    if len(seen) <= 1:
        return ", ".join(f"{k} (weight {v:g})" for k, v in result.views.items())
    return " → ".join(
        f"{i + 1}) " + ", ".join(f"{k} {v:g}" for k, v in views.items())
        for i, views in enumerate(seen)
    )


def render_markdown(result: FitResult, info: ReportInfo, figures: Sequence[str]) -> str:
    """The text of ``report.md``."""
    t = np.asarray(info.target)
    h, w = t.shape
    lines = [f"# Fit report: {info.name}", ""]
    clipped = ""
    if info.saturation is not None:
        n_sat = int(np.sum(t >= info.saturation * (1 - 1e-4)))
        clipped = f", {n_sat} pixels clipped at {info.saturation:g} counts"
    lines += [
        f"- **Target:** `{_rel(info.target_path)}` ({w}×{h} px, "
        f"{info.pixel_scale_deg:.6g} deg/px{clipped})",
        f"- **Model:** `{_rel(info.model_path)}`",
        f"- **Config:** `{_rel(info.config_path)}`",
        f"- **Ground truth:** `{_rel(info.truth_path)}`" if info.truth_path else
        "- **Ground truth:** unknown (a real photo)",
        f"- **Views:** {_stage_views(result)}",
        f"- **Solver:** {result.solver}, {info.n_starts} starts, coarse-to-fine "
        f"{list(info.solver.get('coarse_to_fine', (1,)))}, max_steps "
        f"{info.solver.get('max_steps', '—')}",
        "",
        "## Result",
        "",
        f"- **Status:** {'converged' if result.converged else 'NOT converged'} — "
        f"{result.message}",
        f"- **Loss:** {_fmt(result.loss, 7)} over {result.n_residuals} residuals; "
        f"reduced χ² = {_fmt(result.reduced_chi2, 4)}",
    ]  # fmt: skip
    timing = result.timing_s
    wall = f"; whole command {info.wall_s:.1f} s" if info.wall_s is not None else ""
    lines.append(
        f"- **Time:** compile {timing.get('compile', math.nan):.1f} s, solve "
        f"{timing.get('solve', math.nan):.1f} s, fit {timing.get('total', math.nan):.1f} s"
        + (" (this choice)" if len(info.discrete) > 1 else "")
        + wall
    )
    lines += ["", "## Parameters", ""]
    has_truth = bool(result.truth)
    head = "| parameter | value | ± stderr | unit |"
    rule = "|---|---:|---:|---|"
    if has_truth:
        head += " truth | error | error / stderr |"
        rule += "---:|---:|---:|"
    lines += [head, rule]
    for p in result.paths:
        v, e = result.values[p], result.stderr[p]
        name = f"`{p}`" + (" (nuisance)" if p in result.nuisance else "")
        row = f"| {name} | {_fmt(v, 6)} | {_fmt(e, 3)} | {unit_of(p)} |"
        if has_truth:
            tv = result.truth.get(p) if result.truth else None
            if tv is None:
                row += " — | — | — |"
            else:
                err = v - tv
                z = err / e if e and math.isfinite(e) and e > 0 else math.nan
                row += f" {_fmt(tv, 6)} | {err:+.3g} | {_fmt(z, 3)} |"
        lines.append(row)
    _, table = _discrete_summary(info)
    if table:
        lines += ["", "## Discrete choices", ""]
        for key, entry in table.items():
            truth = entry.get("truth")
            verdict = ""
            if truth is not None:
                verdict = " (the truth)" if truth == entry["value"] else f" (truth: {truth})"
            compared = entry.get("compared_by", {})
            by = ", ".join(f"{k} {v:g}" for k, v in compared.items())
            by = by if compared and compared != result.views else ""
            lines += [
                f"`{key}` = **{entry['value']}**{verdict}, the lowest loss"
                + (f" (views {by}; the chosen value then ran the final stage)" if by else "")
                + " of:",
                "",
                "| value | loss | reduced χ² | converged |",
                "|---:|---:|---:|---|",
            ]
            for c in entry["candidates"]:
                mark = "**" if c["value"] == entry["value"] else ""
                lines.append(
                    f"| {mark}{c['value']}{mark} | {_fmt(c['loss'], 7)} | "
                    f"{_fmt(c['reduced_chi2'], 4)} | {'yes' if c['converged'] else 'no'} |"
                )
            lines.append("")
    for title, section, _ in info.sections.values():
        lines += ["", f"## {title}", "", *section]
    if result.stages:
        first = result.stages[0]
        scan = first.get("scan")
        how = "where each start began and ended."
        if scan:
            by = ", ".join(f"{k} {v:g}" for k, v in scan["views"].items())
            how = (
                f"the starts are the {len(scan['kept'])} lowest-loss of {scan['n_points']} "
                f"points drawn across the bounds (a Latin hypercube, scored by the views {by} "
                "with the flux matched to the unclipped pixels); where each began and ended."
            )
        lines += ["", "## Starts", "", f"Stage 1 (factor {first.get('factor', 1)}): {how}", ""]
        free = [p for p in result.paths if p not in result.nuisance]
        lines.append("| start | " + " | ".join(f"`{p}` (start)" for p in free)
                     + " | final loss | steps | status |")  # fmt: skip
        lines.append("|---:|" + "---:|" * len(free) + "---:|---:|---|")
        for i, start in enumerate(result.starts):
            if i >= len(first.get("final_loss", [])):
                break
            vals = " | ".join(_fmt(start.get(p), 4) for p in free)
            lines.append(
                f"| {i} | {vals} | {_fmt(first['final_loss'][i], 7)} | "
                f"{first['n_steps'][i]} | {first['messages'][i]} |"
            )
    lines += ["", "## Figures", ""]
    captions = {
        "images.png": "Target and model (log scale) and the residual in noise units "
        "(0 at clipped pixels).",
        "profiles.png": "Radial profile and angular energy distribution, target vs model.",
        "loss.png": "Loss at each accepted step of every start"
        + (", and the best loss of each discrete choice." if len(info.discrete) > 1 else "."),
    }
    for f in figures:
        lines += [f"![{f}]({f})", "", captions.get(f, ""), ""]
    return "\n".join(lines).rstrip() + "\n"


def report_dict(result: FitResult, info: ReportInfo) -> dict[str, Any]:
    """The content of ``params.json``: the result's JSON plus the inputs and discrete choices."""
    data = result.to_dict()
    _, table = _discrete_summary(info)
    data["fit"] = {
        "name": info.name,
        "config": _rel(info.config_path),
        "target": _rel(info.target_path),
        "model": _rel(info.model_path),
        "truth": _rel(info.truth_path) if info.truth_path else None,
        "pixel_scale_deg": info.pixel_scale_deg,
        "shape": list(np.asarray(info.target).shape),
        "saturation": info.saturation,
        "n_starts": info.n_starts,
        "wall_s": info.wall_s,
    }
    if table:
        data["discrete"] = table
    for key, (_, _, extra) in info.sections.items():
        data[key] = extra
    return _clean(data)


def write_report(out_dir: str | os.PathLike[str], result: FitResult, info: ReportInfo) -> Path:
    """Write ``report.md``, ``params.json`` and the figures into `out_dir`, atomically as a whole.

    **Returns:** `out_dir` as a `Path`.
    """
    with atomic_directory(out_dir, keep=("posterior",)) as tmp:
        (tmp / "params.json").write_text(dumps_json(report_dict(result, info)) + "\n",
                                         encoding="utf-8")  # fmt: skip
        figures = _figures(tmp, result, info)
        (tmp / "report.md").write_text(render_markdown(result, info, figures), encoding="utf-8")
    return Path(out_dir)
