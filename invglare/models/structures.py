"""Structures the raster may not resolve: checked against its pitch and field when a model is built.

An aperture raster of pitch ``p`` holds spatial frequencies up to ``1 / (2 p)``, i.e. light
diffracted up to ``lambda / (2 p)`` rad, and a model's output covers a field of its own.
What an eye or a camera puts on the raster can be finer than that:

- a **periodic** structure (the lens-fibre gratings of the lenticular halo, a cross-screen
  filter's lines) of period ``L`` diffracts its first order to ``lambda / L``. Below the
  raster's Nyquist period ``2 p`` the sampled grating has another period, and its orders
  land at the wrong angles (a 40 um grating on a 31.5 um raster puts its halo at 0.22 deg
  instead of 0.82 deg): **refused** (:class:`~invglare.errors.PhysicsRangeError`), naming
  the raster it needs. Resolved, its first order can still fall outside the output's
  field: a :class:`RasterWarning` says so;
- a **small** structure (a particle, a lash, a grating's or filter's line, a pixel of an
  obstacle or pupil picture, which is sampled bilinearly) narrower than
  one pitch is drawn as pixel-averaged coverage: its blocked power is right, but its
  diffraction, which spreads to ``lambda / size``, is cut at the raster's band. A
  :class:`RasterWarning` names the raster that would resolve it. (Particles' wide-angle
  scatter beyond the raster's band is what the eye models' ``wide_angle`` term adds.)

:func:`check_structures` runs both checks; the eye and camera models call it from their
``build``.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from typing import Any

import numpy as np

from invglare._core.grids import ApertureGrid
from invglare.errors import PhysicsRangeError, RasterWarning

__all__ = ["RasterWarning", "Structure", "check_structures", "structures_of"]


@dataclasses.dataclass(frozen=True)
class Structure:
    """One structure of an aperture: what it is, whether it is periodic, its size (mm)."""

    name: str
    periodic: bool
    size_mm: float


def _value(x: Any) -> float | None:
    """A concrete float, or None for a traced value (checks then skip it)."""
    try:
        arr = np.asarray(x, dtype=float)
    except Exception:  # a tracer under jit: nothing to check at build time
        return None
    return float(np.min(arr)) if arr.size else None


def _image_pixels(aperture: Any) -> list[tuple[str, bool, Any]]:
    """An image's pixels: sampled bilinearly, so ones finer than the raster alias."""
    out = []
    for name in ("obstacle_image", "pupil_image"):
        image = getattr(aperture, name, None)
        if image is not None:
            cols = image.transmission.shape[1]
            out.append((f"{name} pixels (width_mm / columns)", False, image.width_mm / cols))
    return out


def structures_of(aperture: Any) -> list[Structure]:
    """The periodic and small structures of an eye or camera aperture (others: none)."""
    # Imported here: the aperture classes are below this tier, but not every aperture is one.
    from invglare.aperture.camera import CameraAperture
    from invglare.aperture.eye import EyeAperture

    found: list[tuple[str, bool, Any]] = []
    if isinstance(aperture, EyeAperture):
        g = aperture.gratings
        if g is not None:
            found += [
                ("lens-fibre gratings (spacing_mm)", True, g.spacing_mm),
                ("lens-fibre grating lines (line_thickness_mm)", False, g.line_thickness_mm),
            ]
        for lashes in (aperture.upper_lashes, aperture.lower_lashes):
            if lashes is not None:
                found.append((f"{lashes.lid} lashes (thickness_mm)", False, lashes.thickness_mm))
        for p in aperture.particles:
            found.append(
                (f"{p.region} particles (2 x radius_mean_mm)", False, 2 * p.radius_mean_mm)
            )
        found += _image_pixels(aperture)
    elif isinstance(aperture, CameraAperture):
        f = aperture.filter
        if f is not None:
            found += [
                ("cross-screen lines (spacing_mm)", True, f.spacing_mm),
                (
                    "cross-screen line width (duty_cycle x spacing_mm)",
                    False,
                    np.asarray(f.duty_cycle) * np.asarray(f.spacing_mm),
                ),
            ]
        if aperture.dust is not None:
            found.append(("dust (feature_size_mm)", False, aperture.dust.feature_size_mm))
        found += _image_pixels(aperture)
    out = []
    for name, periodic, size in found:
        value = _value(size)
        if value is not None:
            out.append(Structure(name, periodic, value))
    return out


def check_structures(
    aperture: Any,
    grid: ApertureGrid,
    wavelengths_nm: tuple[float, ...],
    half_field_rad: float | None,
) -> list[Structure]:
    """Refuse periodic structures the raster aliases; warn of what it cannot show.

    **Arguments:**

    - `aperture`: the model's aperture (an eye or camera; others have nothing to check).
    - `grid`: the aperture raster.
    - `wavelengths_nm`: the wavelengths the model computes (their range matters).
    - `half_field_rad`: the output's half field (rad) along an axis, None for an output on
      the image plane (the near field), where only the raster's band limits angles.

    **Returns:** the structures narrower than one pitch (warned of).

    **Raises:** `PhysicsRangeError` for a periodic structure below the raster's Nyquist
    period, naming the `aperture_npix` (at this window) that resolves it.

    **Warns:** :class:`RasterWarning` for a structure narrower than one pitch, and for a
    resolved grating whose first order leaves the output's field.
    """
    pitch = float(grid.pitch_mm)
    width = float(grid.width_mm)
    shortest, longest = min(wavelengths_nm) * 1e-6, max(wavelengths_nm) * 1e-6
    band = (math.degrees(shortest / (2.0 * pitch)), math.degrees(longest / (2.0 * pitch)))
    small = []
    for s in structures_of(aperture):
        if s.periodic:
            if s.size_mm < 2.0 * pitch * (1 - 1e-9):
                needed = math.ceil(2.0 * width / s.size_mm)
                lo, hi = math.degrees(shortest / s.size_mm), math.degrees(longest / s.size_mm)
                raise PhysicsRangeError(
                    f"{s.name} = {s.size_mm * 1e3:.4g} um is below the raster's Nyquist period "
                    f"2 x {pitch * 1e3:.4g} um: sampled, it aliases and puts its first order "
                    f"at the wrong angle (lambda / period = {lo:.3g}-{hi:.3g} deg); use "
                    f"aperture_npix >= "
                    f"{needed} at window_mm = {width:.4g} (pitch <= {s.size_mm * 500:.4g} um)"
                )
            # Resolved (period >= 2 pitch), each colour's order lies inside its own band
            # lambda / (2 pitch); only the output's field can cut it.
            order = longest / s.size_mm
            if half_field_rad is not None and order > float(half_field_rad) * (1 + 1e-9):
                warnings.warn(
                    f"{s.name} = {s.size_mm * 1e3:.4g} um: its first order reaches "
                    f"{math.degrees(order):.3g} deg at {longest * 1e6:.4g} nm, beyond the "
                    f"output's field of +-{math.degrees(float(half_field_rad)):.3g} deg; widen "
                    "the output (npix x pixel_scale_deg)",
                    RasterWarning,
                    stacklevel=3,
                )
        elif s.size_mm < pitch:
            small.append(s)
            warnings.warn(
                f"{s.name} = {s.size_mm * 1e3:.4g} um is narrower than the raster's "
                f"{pitch * 1e3:.4g} um pitch: it is drawn as pixel-averaged coverage, and its "
                f"diffraction (to ~{math.degrees(shortest / s.size_mm):.3g} deg) is cut at the "
                f"raster's band (+-{band[0]:.3g}-{band[1]:.3g} deg); aperture_npix >= "
                f"{math.ceil(width / s.size_mm)} at window_mm = {width:.4g} resolves it",
                RasterWarning,
                stacklevel=3,
            )
    return small
