"""Sampling of the holographic eye: one output grid of directions, one aperture grid per colour.

The holographic eye (Novosad & Ziegler) is computed on grids that all share one size
``N``. Every grid is tied to the **output grid**: ``N x N`` directions spaced
``pixel_scale_rad`` apart in *tangent* space (the frame's perspective pixels: a pixel
``k`` columns right of the centre looks along ``tan(theta_x) = k * dt``). Because the
retinal image is one FFT of the field at the lens (see
:mod:`invglare.optics.holographic.stack`), an FFT bin of the aperture grid *is* an
output pixel when the aperture pitch of wavelength ``lambda`` is

    pitch = lambda / (N dt),      window = N pitch = lambda / dt.

So the colours have different aperture grids (red's window is wider than blue's) and one
output grid: their images superpose pixel for pixel without resampling. The window
limits the optics: the pupil, and the bundle that walks sideways between layers in front
of it, must fit in the *shortest* wavelength's window.

The number of bins across the window is the space-bandwidth product ``N``: a frame of
``N`` pixels over a field of ``N dt`` needs ``N`` samples across ``lambda / dt``. A wide
field through a real pupil is therefore expensive: 20 degrees through a 3 mm pupil at
550 nm is ``3 mm * 0.35 / 550 nm``, about 1900 samples across the pupil alone. The paper's
512 x 512 renderings correspond (at 460-640 nm and an 8-11 mm window) to a field of
about 1.7 degrees.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import equinox as eqx
import numpy as np

from invglare._core.checks import check_static_int
from invglare._core.grids import ApertureGrid, check_wavelengths_nm
from invglare.errors import ConfigError, PhysicsRangeError

__all__ = [
    "HoloSampling",
    "depth_layers_needed",
    "vergence_step_per_mm",
]


class HoloSampling(eqx.Module):
    """The grids of the holographic eye (all static configuration).

    **Fields:**

    - `npix`: grid size ``N`` (output pixels per side = aperture samples per side).
    - `pixel_scale_rad`: output pixel pitch ``dt`` in tangent space (rad for small
      angles).
    - `wavelengths_nm`: one wavelength per colour channel (R, G, B by default).

    Build one with :meth:`from_window` (the shortest wavelength's window is given) or
    directly from the pixel scale.

    **Example:**

    ```python
    s = HoloSampling.from_window(512, 8.0, (640.0, 550.0, 460.0))
    s.pitch_mm(460.0)        # 8 mm / 512 = 0.0156 mm
    s.pixel_scale_deg        # 460 nm / 8 mm = 5.75e-5 rad = 0.0033 deg
    ```
    """

    npix: int = eqx.field(static=True)
    pixel_scale_rad: float = eqx.field(static=True)
    wavelengths_nm: tuple[float, ...] = eqx.field(static=True)

    def __check_init__(self):
        check_static_int("holographic npix", self.npix, 8)
        if self.npix % 2:
            raise ConfigError(f"holographic npix must be even (FFT grid), got {self.npix}")
        dt = self.pixel_scale_rad
        if not (isinstance(dt, float) and math.isfinite(dt) and 0.0 < dt < 0.1):
            raise PhysicsRangeError(
                f"pixel_scale_rad must be a float in (0, 0.1) rad, got {dt!r} (a holographic "
                "grid resolves the pupil's diffraction: its pixels are arc-minutes or less)"
            )
        lams = self.wavelengths_nm
        if not isinstance(lams, tuple) or not lams:
            raise ConfigError(f"wavelengths_nm must be a non-empty tuple, got {lams!r}")
        check_wavelengths_nm(np.asarray(lams, dtype=float))

    @classmethod
    def from_window(
        cls, npix: int, window_mm: float, wavelengths_nm: Sequence[float]
    ) -> HoloSampling:
        """Sampling whose *shortest* wavelength has an aperture window of `window_mm`."""
        lams = tuple(float(w) for w in np.atleast_1d(np.asarray(wavelengths_nm, dtype=float)))
        check_wavelengths_nm(np.asarray(lams))
        if not (math.isfinite(window_mm) and window_mm > 0):
            raise PhysicsRangeError(f"window_mm must be finite and > 0, got {window_mm!r} mm")
        return cls(int(npix), min(lams) * 1e-6 / float(window_mm), lams)

    @classmethod
    def from_pixel_scale(
        cls, npix: int, pixel_scale_deg: float, wavelengths_nm: Sequence[float]
    ) -> HoloSampling:
        """Sampling with output pixels of `pixel_scale_deg` (paraxial: tan dt = dt)."""
        lams = tuple(float(w) for w in np.atleast_1d(np.asarray(wavelengths_nm, dtype=float)))
        if not (math.isfinite(pixel_scale_deg) and pixel_scale_deg > 0):
            raise PhysicsRangeError(
                f"pixel_scale_deg must be finite and > 0, got {pixel_scale_deg!r} deg"
            )
        return cls(int(npix), math.radians(float(pixel_scale_deg)), lams)

    @property
    def pixel_scale_deg(self) -> float:
        """Output pixel pitch in degrees (paraxial: the tangent step as an angle)."""
        return math.degrees(self.pixel_scale_rad)

    @property
    def n_channels(self) -> int:
        return len(self.wavelengths_nm)

    def pitch_mm(self, wavelength_nm: float) -> float:
        """Aperture-grid pitch (mm) of a wavelength: ``lambda / (N dt)``."""
        return float(wavelength_nm) * 1e-6 / (self.npix * self.pixel_scale_rad)

    def window_mm(self, wavelength_nm: float) -> float:
        """Aperture window (mm) of a wavelength: ``lambda / dt``."""
        return float(wavelength_nm) * 1e-6 / self.pixel_scale_rad

    def grid(self, wavelength_nm: float) -> ApertureGrid:
        """The aperture grid of one wavelength (centre pixel ``N // 2`` on the axis)."""
        return ApertureGrid(self.npix, self.pitch_mm(wavelength_nm))

    @property
    def smallest_window_mm(self) -> float:
        return self.window_mm(min(self.wavelengths_nm))

    @property
    def finest_pitch_mm(self) -> float:
        return self.pitch_mm(min(self.wavelengths_nm))

    @property
    def half_field_rad(self) -> float:
        """Largest tangent on the grid (the FFT's Nyquist direction): ``N dt / 2``."""
        return 0.5 * self.npix * self.pixel_scale_rad


def vergence_step_per_mm(
    pupil_diameter_mm: float, wavelength_nm: float, max_opd_waves: float = 0.25
) -> float:
    """The widest vergence step (1/mm) whose rounding keeps the wavefront within tolerance.

    A source at vergence ``V = 1/z`` rounded to a layer at ``V_l`` gets the defocus
    ``(V - V_l)`` across the pupil: an optical path error ``a**2 |V - V_l| / 2`` at the
    pupil's edge (radius ``a``). Rounding to the nearest of layers ``dV`` apart errs by
    at most ``dV / 2``, so the error stays within ``max_opd_waves * lambda`` when

        dV <= 4 max_opd_waves lambda / a**2.

    With the default quarter wave (Rayleigh's criterion; for pure defocus it is a Strehl
    ratio of 0.80 by Marechal's approximation, ``rms = W / sqrt(12)``), ``dV = lambda / a**2``.
    """
    if not (pupil_diameter_mm > 0 and wavelength_nm > 0 and max_opd_waves > 0):
        raise PhysicsRangeError(
            "vergence step needs a pupil diameter, wavelength and tolerance > 0, got "
            f"{pupil_diameter_mm!r} mm, {wavelength_nm!r} nm, {max_opd_waves!r} waves"
        )
    a = 0.5 * float(pupil_diameter_mm)
    return 4.0 * float(max_opd_waves) * float(wavelength_nm) * 1e-6 / (a * a)


def depth_layers_needed(
    near_mm: float,
    far_mm: float,
    pupil_diameter_mm: float,
    wavelength_nm: float,
    max_opd_waves: float = 0.25,
) -> int:
    """How many depth layers a depth range needs so that no source is defocused by rounding.

    Layers are spaced evenly in vergence ``1/z`` (defocus is linear in it, not in ``z``),
    from ``1/far`` to ``1/near``; each source goes to the nearest. The count is
    ``ceil((1/near - 1/far) / dV)`` with the step of :func:`vergence_step_per_mm`; use
    the *shortest* wavelength and the *largest* pupil the eye will have.

    **Arguments:**

    - `near_mm`, `far_mm`: nearest and farthest depth (mm, ``0 < near <= far``; `far`
      may be ``inf``).
    - `pupil_diameter_mm`: pupil diameter (mm).
    - `wavelength_nm`: wavelength (nm).
    - `max_opd_waves`: largest optical path error from rounding, in waves (0.25).

    **Returns:** the number of layers (>= 1).

    **Example:**

    ```python
    depth_layers_needed(500.0, math.inf, 3.0, 460.0)   # 2 D * (1.5 mm)^2 / 460 nm -> 10
    ```
    """
    if not (near_mm > 0 and far_mm >= near_mm):
        raise PhysicsRangeError(
            f"depth range must have 0 < near <= far, got near {near_mm!r} mm, far {far_mm!r} mm"
        )
    span = 1.0 / near_mm - (0.0 if math.isinf(far_mm) else 1.0 / far_mm)
    step = vergence_step_per_mm(pupil_diameter_mm, wavelength_nm, max_opd_waves)
    # A relative slack absorbs round-off when the span is an exact multiple of the step.
    return max(1, math.ceil(span / step * (1.0 - 1e-12)))
