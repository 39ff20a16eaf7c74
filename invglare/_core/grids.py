"""Grids and units: the aperture plane and the output (angular) plane.

Conventions used throughout invglare:

* Both planes are square grids whose *centre pixel* has index ``npix // 2`` and
  sits at coordinate 0 (the FFT convention, for even and odd sizes alike).
  Coordinates of pixel ``k`` are ``(k - npix // 2) * pitch``. Row index is y,
  column index is x; y points up in physical terms but arrays are stored
  row-major with row 0 first, exactly as the coordinates say.
* Aperture-plane lengths are in mm; output-plane positions are angles
  (degrees in the public API, radians inside). The Fraunhofer pattern at angle
  ``theta`` samples the aperture's Fourier transform at spatial frequency
  ``theta / wavelength`` (paraxial, ``theta`` in rad). On the retina / sensor,
  at focal distance ``f``, the angle corresponds to ``x = f * tan(theta)``.
* The FFT of an aperture of pitch ``d`` zero-padded to ``M`` samples gives
  output pixels of ``wavelength / (M * d)`` rad; the matrix Fourier transform
  accepts any output pixel scale.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from invglare._core.checks import check_positive, is_concrete, shown
from invglare.errors import PhysicsRangeError

#: Wavelengths outside this range (nm) are refused: they are almost always a unit mistake.
WAVELENGTH_RANGE_NM = (100.0, 20000.0)


def nm_to_mm(wavelength_nm: ArrayLike) -> Array:
    """Convert a wavelength in nm to mm (the aperture-plane length unit)."""
    return jnp.asarray(wavelength_nm) * 1e-6


def deg_to_rad(angle_deg: ArrayLike) -> Array:
    return jnp.asarray(angle_deg) * (math.pi / 180.0)


def rad_to_deg(angle_rad: ArrayLike) -> Array:
    return jnp.asarray(angle_rad) * (180.0 / math.pi)


def check_wavelengths_nm(wavelengths_nm) -> None:
    """Refuse wavelengths that are not in nanometres (e.g. given in metres or micrometres)."""
    if not is_concrete(wavelengths_nm):
        return
    arr = np.atleast_1d(np.asarray(wavelengths_nm, dtype=float))
    lo, hi = WAVELENGTH_RANGE_NM
    if arr.size == 0:
        raise PhysicsRangeError("wavelengths_nm is empty; expected at least one wavelength in nm")
    if not np.all(np.isfinite(arr)):
        raise PhysicsRangeError(f"wavelengths_nm must be finite, got {shown(arr)}")
    if np.any((arr < lo) | (arr > hi)):
        bad = arr[(arr < lo) | (arr > hi)][0]
        hint = ""
        if bad <= 0:
            hint = " (a wavelength is a positive length)"
        elif bad < 1e-3:
            hint = " (it looks like metres: 550 nm is 5.5e-07 m)"
        elif bad < 30:
            hint = " (it looks like micrometres: 550 nm is 0.55 um)"
        raise PhysicsRangeError(
            f"wavelength {bad:g} nm is outside {lo:g}-{hi:g} nm{hint}; give wavelengths in nm"
        )


class ApertureGrid(eqx.Module):
    """A square grid of `npix` x `npix` samples of pitch `pitch_mm` in the aperture plane."""

    npix: int = eqx.field(static=True)
    pitch_mm: Float[Array, ""] = eqx.field(converter=jnp.asarray)

    def __check_init__(self):
        if self.npix < 2:
            raise PhysicsRangeError(f"aperture npix must be >= 2, got {self.npix}")
        check_positive("aperture pitch_mm", self.pitch_mm, "mm")

    @classmethod
    def from_width(cls, npix: int, width_mm: float) -> ApertureGrid:
        """A grid of `npix` samples spanning `width_mm` (pitch = width / npix)."""
        check_positive("aperture window_mm", width_mm, "mm")
        return cls(npix, jnp.asarray(width_mm) / npix)

    @property
    def width_mm(self) -> Float[Array, ""]:
        return self.pitch_mm * self.npix

    def coords_mm(self) -> Float[Array, " npix"]:
        """Pixel-centre coordinates along one axis, 0 at index ``npix // 2``."""
        return (jnp.arange(self.npix) - self.npix // 2) * self.pitch_mm

    def mesh_mm(self) -> tuple[Float[Array, "npix npix"], Float[Array, "npix npix"]]:
        """``(y, x)`` coordinate arrays, indexed ``[row, column]``."""
        c = self.coords_mm()
        return c[:, None] * jnp.ones((1, self.npix)), jnp.ones((self.npix, 1)) * c[None, :]

    def max_frequency_per_mm(self) -> Float[Array, ""]:
        """Nyquist frequency of the grid: beyond it the sampled aperture's spectrum aliases."""
        return 0.5 / self.pitch_mm


class AngularGrid(eqx.Module):
    """The output grid: `npix` x `npix` pixels of `pixel_scale_deg` degrees each."""

    npix: int = eqx.field(static=True)
    pixel_scale_deg: Float[Array, ""] = eqx.field(converter=jnp.asarray)

    def __check_init__(self):
        if self.npix < 1:
            raise PhysicsRangeError(f"output npix must be >= 1, got {self.npix}")
        check_positive("pixel_scale_deg", self.pixel_scale_deg, "deg")

    @property
    def pixel_scale_rad(self) -> Float[Array, ""]:
        return deg_to_rad(self.pixel_scale_deg)

    def coords_rad(self) -> Float[Array, " npix"]:
        """Pixel-centre angles along one axis (rad), 0 at index ``npix // 2``."""
        return (jnp.arange(self.npix) - self.npix // 2) * self.pixel_scale_rad

    def coords_deg(self) -> Float[Array, " npix"]:
        return (jnp.arange(self.npix) - self.npix // 2) * self.pixel_scale_deg

    @property
    def half_field_deg(self) -> Float[Array, ""]:
        """Largest angle from the centre along an axis (deg)."""
        return self.pixel_scale_deg * (self.npix // 2)

    def solid_angle_sr(self) -> Float[Array, ""]:
        """Solid angle of one pixel (small-angle approximation), for PSFs in sr^-1."""
        return self.pixel_scale_rad**2


class Sampling(eqx.Module):
    """Ties an aperture grid, an output grid and a focal distance together.

    With it, output pixels can be read as angles (deg), as positions on the
    retina / sensor (um, at `focal_length_mm`), or as spatial frequencies of
    the aperture at a given wavelength.
    """

    aperture: ApertureGrid
    output: AngularGrid
    focal_length_mm: Float[Array, ""] = eqx.field(converter=jnp.asarray)

    def __check_init__(self):
        check_positive("focal_length_mm", self.focal_length_mm, "mm")

    def retina_pitch_um(self) -> Float[Array, ""]:
        """Size of one output pixel on the image plane (um), ``f * tan(pixel scale)``."""
        return self.focal_length_mm * jnp.tan(self.output.pixel_scale_rad) * 1e3

    def frequencies_per_mm(self, wavelength_nm: ArrayLike) -> Float[Array, " npix"]:
        """Aperture spatial frequencies (cycles/mm) sampled by the output grid at a wavelength."""
        return self.output.coords_rad() / nm_to_mm(wavelength_nm)

    def fft_pixel_scale_deg(self, wavelength_nm: ArrayLike, fft_npix: int) -> Float[Array, ""]:
        """Output pixel scale (deg) of an FFT of the aperture zero-padded to `fft_npix`."""
        return rad_to_deg(nm_to_mm(wavelength_nm) / (fft_npix * self.aperture.pitch_mm))

    def fft_npix_for(self, wavelength_nm: float) -> float:
        """FFT size (not rounded) whose native pixel scale equals the output grid's."""
        lam_mm = float(wavelength_nm) * 1e-6
        return lam_mm / (float(self.aperture.pitch_mm) * float(self.output.pixel_scale_rad))

    def alias_free(self, wavelength_nm: float) -> bool:
        """Whether the output field stays inside the aperture grid's Nyquist band."""
        f_max = float(self.output.half_field_deg) * math.pi / 180.0 / (float(wavelength_nm) * 1e-6)
        return f_max <= float(self.aperture.max_frequency_per_mm()) * (1 + 1e-6)  # ties pass
