"""A propagator: from an aperture field to a unit-energy PSF on a chosen output grid.

It bundles the aperture raster, the output grid, the focal distance, the
propagation (Fraunhofer, or Fresnel with the quadratic phase of eq. 3 of the
temporal-glare paper) and the transform (FFT or matrix Fourier transform), and
:meth:`Propagator.build` makes and validates those choices once. Every forward
model uses one, so the sampling rules live in a single place.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Inexact

from invglare._core.grids import AngularGrid, ApertureGrid, check_positive
from invglare.errors import ConfigError, PhysicsRangeError
from invglare.optics.fraunhofer import fraunhofer_mft, intensity_fft
from invglare.optics.fresnel import fresnel_phase

PROPAGATIONS = ("fraunhofer", "fresnel")
METHODS = ("auto", "fft", "mft")

#: Largest FFT the automatic method choice will pick before falling back to the MFT.
MAX_AUTO_FFT_NPIX = 4096


def choose(name: str, value: str, valid: Sequence[str]) -> str:
    """Return `value` if it is one of `valid`, else raise a ConfigError listing them."""
    if value not in valid:
        raise ConfigError(f"{name} = {value!r} is not one of {', '.join(valid)}")
    return value


def _check_npix(name: str, value: int, minimum: int) -> int:
    if int(value) != value or value < minimum:
        raise PhysicsRangeError(f"{name} must be an integer >= {minimum}, got {value}")
    return int(value)


class Propagator(eqx.Module):
    """Aperture field → unit-energy PSF (see :mod:`invglare.optics.fraunhofer`)."""

    grid: ApertureGrid
    output: AngularGrid
    focal_length_mm: Float[Array, ""] = eqx.field(converter=jnp.asarray)
    propagation: str = eqx.field(static=True, default="fraunhofer")
    method: str = eqx.field(static=True, default="mft")
    fft_npix: int = eqx.field(static=True, default=0)

    @classmethod
    def build(
        cls,
        *,
        window_mm: float,
        focal_length_mm: float,
        fft_wavelength_nm: float,
        shortest_wavelength_nm: float,
        npix: int = 512,
        pixel_scale_deg: float | None = None,
        aperture_npix: int = 256,
        propagation: str = "fraunhofer",
        method: str = "auto",
    ) -> Propagator:
        """Choose the transform for a sampling, refusing ones that would alias.

        **Arguments:**

        - `window_mm`, `aperture_npix`: the aperture raster (pitch = window / npix).
        - `focal_length_mm`: pupil-to-retina / lens-to-sensor distance (Fresnel term).
        - `fft_wavelength_nm`: the wavelength an FFT is computed at (it fixes the FFT
          pixel scale ``lambda / (fft_npix * pitch)``).
        - `shortest_wavelength_nm`: the shortest wavelength an MFT will evaluate; the
          output field must stay within its alias-free band.
        - `npix`, `pixel_scale_deg`: the output grid; without a pixel scale, the FFT's
          native one (with ``fft_npix = max(npix, 2 * aperture_npix)``).
        - `method`: ``"fft"``, ``"mft"`` or ``"auto"`` (the FFT when it produces the
          requested pixel scale exactly, else the MFT).
        """
        choose("propagation", propagation, PROPAGATIONS)
        choose("method", method, METHODS)
        npix = _check_npix("npix", npix, 8)
        aperture_npix = _check_npix("aperture_npix", aperture_npix, 8)
        check_positive("window_mm", window_mm, "mm")
        check_positive("focal_length_mm", focal_length_mm, "mm")
        pitch = window_mm / aperture_npix
        if pixel_scale_deg is None:
            if method == "mft":
                raise ConfigError("method = 'mft' needs pixel_scale_deg")
            fft_npix = max(npix, 2 * aperture_npix)
            fft_npix += fft_npix % 2
            pixel_scale_deg = math.degrees(fft_wavelength_nm * 1e-6 / (fft_npix * pitch))
            method = "fft"
        else:
            check_positive("pixel_scale_deg", pixel_scale_deg, "deg")
            ideal = fft_wavelength_nm * 1e-6 / (pitch * math.radians(pixel_scale_deg))
            fft_npix = round(ideal)
            exact = abs(ideal - fft_npix) < 1e-6 * ideal
            fits = exact and fft_npix >= aperture_npix and fft_npix >= npix
            if method == "auto":
                method = "fft" if fits and fft_npix <= MAX_AUTO_FFT_NPIX else "mft"
            elif method == "fft" and not fits:
                raise ConfigError(
                    f"method = 'fft' gives pixels of lambda / (M * pitch); pixel_scale_deg = "
                    f"{pixel_scale_deg:g} needs M = {ideal:.3f}, not an integer >= npix "
                    "(drop pixel_scale_deg, or use method = 'mft')"
                )
            if method == "mft":
                fft_npix = 0
        output = AngularGrid(npix, pixel_scale_deg)
        if propagation == "fresnel":
            # The quadratic phase must be sampled: its local frequency r / (lambda d) at the
            # window's edge has to stay under Nyquist, or the "PSF" is aliasing noise.
            edge_mm = window_mm / 2
            chirp = edge_mm / (shortest_wavelength_nm * 1e-6 * focal_length_mm)
            if chirp > 0.5 / pitch:
                needed = math.ceil(2 * chirp * window_mm)
                raise PhysicsRangeError(
                    f"the Fresnel phase (eq. 3) aliases: at {edge_mm:g} mm from the axis it "
                    f"oscillates at {chirp:.4g} cycles/mm, above the {0.5 / pitch:.4g} the "
                    f"aperture raster resolves; use aperture_npix >= {needed}, a longer "
                    "focal_length_mm, or propagation = 'fraunhofer'"
                )
        if method == "mft":
            half_field = math.radians(float(output.half_field_deg))
            # A relative margin: a field exactly at the band edge (the FFT's own) is fine
            # and must not be refused for a float32 rounding error.
            if half_field / (shortest_wavelength_nm * 1e-6) > 0.5 / pitch * (1 + 1e-6):
                supported = math.degrees(0.5 / pitch * shortest_wavelength_nm * 1e-6)
                raise PhysicsRangeError(
                    f"the output field reaches {float(output.half_field_deg):.4g} deg but the "
                    f"aperture sampling (pitch {pitch * 1e3:.3g} um) supports only "
                    f"{supported:.4g} deg at {shortest_wavelength_nm:g} nm without aliasing; "
                    "raise aperture_npix or lower npix / pixel_scale_deg"
                )
        return cls(
            grid=ApertureGrid.from_width(aperture_npix, window_mm),
            output=output,
            focal_length_mm=focal_length_mm,
            propagation=propagation,
            method=method,
            fft_npix=fft_npix,
        )

    def __call__(
        self, field: Inexact[Array, "n n"], wavelength_nm: ArrayLike
    ) -> Float[Array, "npix npix"]:
        """Unit-energy PSF of `field` at one wavelength (FFT path: at the FFT's own scale)."""
        if self.propagation == "fresnel":
            field = field * fresnel_phase(self.grid, wavelength_nm, self.focal_length_mm)
        if self.method == "fft":
            return intensity_fft(field, self.fft_npix, self.output.npix)
        return fraunhofer_mft(field, self.grid, wavelength_nm, self.output)
