"""The ghosts of a fitted veiling model, set against the true ones.

A veiling-glare fit adjusts lens parameters (coating reflectances, the light's
direction); what a user checks is whether each *ghost* came out right: its position on
the screen (pixels) and its intensity. :func:`ghost_section` derives both from the
fitted and the true model (``VeilingGlare.ghosts_at``) for the report.

**Example:**

```python
lines, data = ghost_section(fitted_model, true_model)
print("\\n".join(lines))           # a markdown table, one row per ghost
data["max_position_error_px"]     # worst ghost position error, pixels
```
"""

from __future__ import annotations

from typing import Any

import numpy as np

from invglare.models.veiling import VeilingGlare


def _ghosts(model: VeilingGlare) -> dict[str, np.ndarray]:
    g = model.ghosts_at()
    intensity, radius = model.drawn(g)
    return {
        "position_px": np.asarray(g.position_deg, dtype=float) / model.pixel_scale_deg,
        "radius_px": np.asarray(radius, dtype=float) / model.pixel_scale_deg,
        "intensity_per_sr": np.asarray(intensity, dtype=float),
    }


def ghost_section(
    fitted: VeilingGlare, truth: VeilingGlare | None = None
) -> tuple[list[str], dict[str, Any]]:
    """Markdown lines and JSON data: each ghost's position (px from the screen centre),
    drawn radius and intensity, fitted and (with `truth`) true, with the errors.

    Positions are the ghosts' centres in the model's pixels, x along the columns and y
    along the rows from the optical axis at pixel ``(ny // 2, nx // 2)``; a ghost whose
    centre lies off the screen is still listed (its edge may cross it). Ghosts the model
    does not draw (zero intensity) are left out of the worst-error summary.
    """
    fit = _ghosts(fitted)
    true = _ghosts(truth) if truth is not None else None
    k = fit["intensity_per_sr"].shape[0]
    ny, nx = fitted.npix
    on_screen = np.all(np.abs(fit["position_px"]) <= [nx / 2, ny / 2], axis=-1)
    data: dict[str, Any] = {
        "n_ghosts": int(k),
        "fitted": {key: v.tolist() for key, v in fit.items()},
        "centre_on_screen": on_screen.tolist(),
    }
    header = "| ghost | x px | y px | radius px | intensity (sr⁻¹) |"
    rule = "|---:|---:|---:|---:|---:|"
    if true is not None:
        d_pos = np.linalg.norm(fit["position_px"] - true["position_px"], axis=-1)
        drawn = true["intensity_per_sr"] > 0
        rel = np.where(
            drawn, fit["intensity_per_sr"] / np.where(drawn, true["intensity_per_sr"], 1) - 1, 0
        )
        data["truth"] = {key: v.tolist() for key, v in true.items()}
        data["position_error_px"] = d_pos.tolist()
        data["intensity_rel_error"] = rel.tolist()
        data["max_position_error_px"] = float(np.max(d_pos[drawn], initial=0.0))
        data["max_intensity_rel_error"] = float(np.max(np.abs(rel[drawn]), initial=0.0))
        header += " true x, y px | position error px | true intensity | intensity error |"
        rule += "---:|---:|---:|---:|"
    lines = [
        f"{k} ghosts of the fitted lens for the fitted light direction, positions in pixels "
        "from the optical axis (x along the columns, y along the rows); * marks a ghost "
        "centred off the screen.",
        "",
    ]
    if true is not None:
        lines[0] += (
            f" Worst errors over the drawn ghosts: position **{data['max_position_error_px']:.3g} "
            f"px**, intensity **{100 * data['max_intensity_rel_error']:.3g} %**."
        )
    lines += [header, rule]
    for i in range(k):
        (x, y), r, inten = fit["position_px"][i], fit["radius_px"][i], fit["intensity_per_sr"][i]
        mark = "" if on_screen[i] else "*"
        row = f"| {i}{mark} | {x:.2f} | {y:.2f} | {r:.1f} | {inten:.4g} |"
        if true is not None:
            tx, ty = true["position_px"][i]
            row += (
                f" {tx:.2f}, {ty:.2f} | {data['position_error_px'][i]:.3f} | "
                f"{true['intensity_per_sr'][i]:.4g} | "
                f"{100 * data['intensity_rel_error'][i]:+.2f} % |"
            )
        lines.append(row)
    return lines, data


__all__ = ["ghost_section"]


def ghost_report_sections(
    fitted: VeilingGlare, truth: VeilingGlare | None = None
) -> dict[str, tuple[str, list[str], dict[str, Any]]]:
    """The report sections of a veiling fit: ``{"ghosts": ("Ghosts", lines, data)}``."""
    lines, data = ghost_section(fitted, truth)
    return {"ghosts": ("Ghosts", lines, data)}
