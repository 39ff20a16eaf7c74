"""How a recomputed PSF is compared with its golden: five metrics and a config diff.

**Metrics** (``ref`` the stored PSF, ``new`` the recomputed one, ``peak = max(ref)``;
RGB PSFs are compared over all three channels):

- `rel_l2`: ``‖new − ref‖₂ / ‖ref‖₂``;
- `max_err`: ``max |new − ref| / peak``;
- `ssim_log`: SSIM (scikit-image `structural_similarity`, 7×7 window, data range 1) of
  the **log-scaled** images ``clip(1 + log10(x / peak) / 6, 0, 1)`` (six decades below
  the reference peak, both images on the same scale);
- `psnr_db`: PSNR (scikit-image `peak_signal_noise_ratio`) of the linear images, data
  range ``peak``; ``inf`` for identical images;
- `ee_diff`: ``max_r |EE_new(r) − EE_ref(r)|``, the encircled energy as a fraction of
  the unit-energy PSF at radii 1, 2, 4, … px up to the half-width, per channel.

SSIM is taken on the log-scaled images because a PSF spans six or more decades and
its glare (streaks, halos, the ciliary corona) lives far below the peak, where a
linear SSIM would see nothing; the linear metrics (L2, max error, PSNR) watch the
core. The bounds a case must meet are its :class:`~invglare.regress.cases.Tolerance`.

**Example:**

```python
m = compare_psfs(golden, psf, 0.004)
m.failures(DEFAULT_TOLERANCE)   # [] when it passes
```
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
from jaxtyping import Float

from invglare.errors import InputDataError
from invglare.regress.cases import Tolerance

__all__ = ["LOG_DECADES", "Metrics", "compare_psfs", "config_changes", "log_scaled", "metric_cells"]

#: Decades below the reference peak shown by the log-scaled images (SSIM, figures).
LOG_DECADES = 6.0


@dataclasses.dataclass(frozen=True)
class Metrics:
    """Differences of a recomputed PSF from its golden (module docstring: definitions)."""

    rel_l2: float
    max_err: float
    ssim_log: float
    psnr_db: float
    ee_diff: float

    def failures(self, tol: Tolerance) -> list[str]:
        """The metrics outside `tol`, as ``"rel_l2 1.2e-3 > 3e-5"`` strings."""
        out = []
        for name, value, limit, worse in (
            ("rel_l2", self.rel_l2, tol.rel_l2, self.rel_l2 > tol.rel_l2),
            ("max_err", self.max_err, tol.max_err, self.max_err > tol.max_err),
            ("ssim_log", self.ssim_log, tol.ssim_log, self.ssim_log < tol.ssim_log),
            ("psnr_db", self.psnr_db, tol.psnr_db, self.psnr_db < tol.psnr_db),
            ("ee_diff", self.ee_diff, tol.ee_diff, self.ee_diff > tol.ee_diff),
        ):
            # NaN compares False everywhere: treat it as a failure explicitly.
            if worse or math.isnan(value):
                sign = "<" if name in ("ssim_log", "psnr_db") else ">"
                out.append(f"{name} {value:.3g} {sign} {limit:g}")
        return out


def log_scaled(
    image: Float[np.ndarray, "*shape"], peak: float, decades: float = LOG_DECADES
) -> Float[np.ndarray, "*shape"]:
    """``clip(1 + log10(image / peak) / decades, 0, 1)``: a PSF as a [0, 1] image.

    **Example:** ``log_scaled(psf, psf.max())`` maps the peak to 1 and 1e-6 of it to 0.
    """
    ratio = np.maximum(np.asarray(image, dtype=np.float64) / peak, 10.0 ** (-2 * decades))
    return np.clip(1.0 + np.log10(ratio) / decades, 0.0, 1.0)


def _ee_radii_px(npix: int) -> np.ndarray:
    radii = [1.0]
    while radii[-1] * 2 < npix // 2 - 1:
        radii.append(radii[-1] * 2)
    radii.append(float(npix // 2 - 1))
    return np.asarray(radii)


def compare_psfs(
    reference: Float[np.ndarray, "h w *c"],
    new: Float[np.ndarray, "h w *c"],
    pixel_scale_deg: float,
) -> Metrics:
    """The five metrics of `new` against `reference` (module docstring).

    **Raises:** `InputDataError` when the shapes differ (a changed grid is a failure
    of its own, not something to interpolate over).

    **Example:**

    ```python
    m = compare_psfs(golden, psf, 0.004)
    m.failures(DEFAULT_TOLERANCE)   # [] when it passes
    ```
    """
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    from invglare.reference.profiles import encircled_energy

    ref = np.asarray(reference, dtype=np.float64)
    cur = np.asarray(new, dtype=np.float64)
    if ref.shape != cur.shape:
        raise InputDataError(
            f"the recomputed PSF has shape {cur.shape} but the golden has {ref.shape}"
        )
    peak = float(np.max(ref))
    if not peak > 0:
        raise InputDataError(f"the golden PSF has no positive value (max {peak:g})")
    diff = cur - ref
    rel_l2 = float(np.linalg.norm(diff) / np.linalg.norm(ref))
    max_err = float(np.max(np.abs(diff)) / peak)
    rgb = ref.ndim == 3
    ssim = float(
        structural_similarity(
            log_scaled(ref, peak),
            log_scaled(cur, peak),
            data_range=1.0,
            channel_axis=-1 if rgb else None,
        )
    )
    if np.any(diff):
        psnr = float(peak_signal_noise_ratio(ref, cur, data_range=peak))
    else:
        psnr = math.inf  # skimage divides by a zero MSE (and warns) for identical images
    radii = _ee_radii_px(ref.shape[0]) * pixel_scale_deg
    planes_ref = ref if rgb else ref[..., None]
    planes_cur = cur if rgb else cur[..., None]
    # Channels first for the batched encircled energy; total=1: the PSFs are fractions.
    ee_ref, ee_cur = (
        np.asarray(encircled_energy(np.moveaxis(p, -1, 0), pixel_scale_deg, radii, total=1.0))
        for p in (planes_ref, planes_cur)
    )
    ee = float(np.max(np.abs(ee_cur - ee_ref)))
    return Metrics(rel_l2=rel_l2, max_err=max_err, ssim_log=ssim, psnr_db=psnr, ee_diff=ee)


def config_changes(stored: Any, current: Any, prefix: str = "") -> list[str]:
    """Dotted keys where two JSON-like configs differ (numbers to a relative 1e-5).

    1e-5 rather than float32's 6e-8: EXR float attributes come back through a decimal
    rounding that, once colour-science has set numpy's legacy print options, keeps only
    six significant digits.
    """
    if isinstance(stored, dict) and isinstance(current, dict):
        out = []
        for key in sorted(set(stored) | set(current), key=str):
            where = f"{prefix}.{key}" if prefix else str(key)
            if key not in stored or key not in current:
                out.append(where)
            else:
                out.extend(config_changes(stored[key], current[key], where))
        return out
    if isinstance(stored, list) and isinstance(current, list):
        if len(stored) != len(current):
            return [prefix]
        out = []
        for i, (a, b) in enumerate(zip(stored, current, strict=True)):
            out.extend(config_changes(a, b, f"{prefix}[{i}]"))
        return out
    if isinstance(stored, int | float) and isinstance(current, int | float):
        same = math.isclose(float(stored), float(current), rel_tol=1e-5, abs_tol=1e-12)
        return [] if same else [prefix]
    return [] if stored == current else [prefix]


def metric_cells(m: Metrics | None) -> list[str]:
    """The five metrics as table cells (``–`` for none), in the report's column order."""
    if m is None:
        return ["–"] * 5
    psnr = "inf" if math.isinf(m.psnr_db) else f"{m.psnr_db:.1f}"
    return [f"{m.rel_l2:.2e}", f"{m.max_err:.2e}", f"{m.ssim_log:.6f}", psnr, f"{m.ee_diff:.2e}"]
