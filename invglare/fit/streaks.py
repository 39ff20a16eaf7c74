"""Lash directions read off a photo: each lash diffracts light into a streak across itself.

A thin lash crossing the pupil spreads light into a streak perpendicular to it, so the
angular energy of a glare photo (energy per direction in an annulus around the source)
shows a peak for every direction lashes point in. With the convention of
:class:`~invglare.aperture.eye.Eyelashes` (a lash's angle is measured from its margin's
normal into the opening, counter-clockwise), a straight lash at angle ``a`` makes a
streak at ``a`` (modulo 180°) in the angles of :func:`~invglare.fit.views.angular_energy`,
for the upper and the lower lid alike; a lash bent by ``curvature`` over its ``length``
points on average ``curvature * length / 2`` radians further.

:func:`streak_directions` folds the angular energy of the photo (outside the core, where
the streaks stand above the diffraction of the pupil's rim) onto 180°, takes what
stands above its median as the streaks' energy, and returns their mean direction and
spread (circular statistics on doubled angles). :func:`lash_guesses` turns that into
starting values of a row's `mean_angle_deg` and `angular_spread_deg`: a fit of an eye
whose lashes it did not draw starts from the photo, not from the model's config.

**Example:**

```python
mean_deg, spread_deg = streak_directions(photo, (64.3, 63.8), background=20.0)
```
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
from jaxtyping import ArrayLike, Float

from invglare.fit.views import angular_bin_angles_deg, angular_energy

#: Sectors of the folded angular energy (1° each over 180°).
N_SECTORS = 180

#: The streak of one lash is about this many sectors wide (intrinsic width, removed from
#: the spread in quadrature).
_STREAK_WIDTH_DEG = 2.0


def streak_directions(
    photo: Float[ArrayLike, "h w"],
    centre: tuple[float, float],
    *,
    background: float = 0.0,
    r_min_px: float | None = None,
    r_max_px: float | None = None,
) -> tuple[float, float]:
    """Mean direction and spread (deg) of the streaks of a glare photo, modulo 180°.

    **Arguments:**

    - `photo`: the photo in counts, ``(h, w)``.
    - `centre`: the source's position ``(x, y)`` in pixel index units.
    - `background`: counts per pixel to remove first.
    - `r_min_px`, `r_max_px`: the annulus (default: from a tenth of the half-width, past
      the core, to the edge).

    **Returns:** ``(mean, spread)`` in degrees; the mean in ``(-90, 90]``, in the angles
    of :func:`~invglare.fit.views.angular_energy`. ``(nan, nan)`` when nothing stands out.
    """
    img = np.asarray(photo, dtype=np.float64) - float(background)
    half = min(img.shape) // 2 - 1
    r_min = max(4.0, 0.1 * half) if r_min_px is None else float(r_min_px)
    r_max = float(half) if r_max_px is None else float(r_max_px)
    energy = np.asarray(angular_energy(img, centre, 2 * N_SECTORS, r_min, r_max))
    folded = energy[:N_SECTORS] + energy[N_SECTORS:]
    excess = np.maximum(folded - np.median(folded), 0.0)
    if not np.any(excess > 0):
        return math.nan, math.nan
    phi = np.deg2rad(angular_bin_angles_deg(2 * N_SECTORS)[:N_SECTORS])
    z = np.sum(excess * np.exp(2j * phi)) / np.sum(excess)
    mean = 0.5 * math.degrees(math.atan2(z.imag, z.real))
    # Circular spread on doubled angles, halved; the streaks' own width removed.
    r = min(max(abs(z), 1e-12), 1.0)
    spread = 0.5 * math.degrees(math.sqrt(-2.0 * math.log(r)))
    spread = math.sqrt(max(spread**2 - _STREAK_WIDTH_DEG**2, 0.0))
    return (mean if mean > -90.0 else mean + 180.0), spread


def lash_guesses(
    photo: Float[ArrayLike, "h w"],
    forward: Any,
    guesses: Mapping[str, float],
) -> dict[str, float]:
    """Starting values of the lash rows' mean angle and spread, from the photo's streaks.

    For each row of lashes of `forward`'s model (``model.aperture.upper_lashes``,
    ``model.aperture.lower_lashes``), ``{path: value}`` of its `mean_angle_deg` (the
    streaks' mean direction less the mean bend ``curvature * length / 2`` of the row's
    lashes) and `angular_spread_deg`. `guesses` supply the centre and background
    (:func:`~invglare.fit.starts.photo_guesses`). Empty when the model has no lashes or
    the photo shows no streaks.
    """
    aperture = getattr(forward.model, "aperture", None)
    rows = [(name, getattr(aperture, name, None)) for name in ("upper_lashes", "lower_lashes")]
    rows = [(name, row) for name, row in rows if row is not None and hasattr(row, "mean_angle_deg")]
    if not rows:
        return {}
    h, w = np.shape(photo)
    centre = (w // 2 + guesses.get("obs.dx_px", 0.0), h // 2 + guesses.get("obs.dy_px", 0.0))
    mean, spread = streak_directions(photo, centre, background=guesses.get("obs.background", 0.0))
    if not math.isfinite(mean):
        return {}
    out = {}
    for name, row in rows:
        bend = math.degrees(0.5 * float(row.curvature_per_mm) * float(row.length_mm))
        angle = (mean - bend + 90.0) % 180.0 - 90.0
        out[f"model.aperture.{name}.mean_angle_deg"] = angle
        out[f"model.aperture.{name}.angular_spread_deg"] = spread
    return out
