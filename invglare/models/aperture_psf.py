"""The PSF of a static aperture: the simplest forward model, and the base of the others.

An :class:`AperturePSF` rasterises an :class:`~invglare.aperture.Aperture`,
propagates it to the far field (Fraunhofer) or applies the Fresnel term of the
temporal-glare paper first (eq. 3), and returns

* a monochrome PSF ``(npix, npix)`` when it has one wavelength, or
* a linear RGB PSF ``(npix, npix, 3)`` integrated over its wavelengths,

normalised as in :mod:`invglare.optics.fraunhofer` (fraction of the transmitted
power per pixel; for RGB the luminance Y carries that normalisation).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from invglare.aperture import Aperture
from invglare.errors import ConfigError, PhysicsRangeError
from invglare.optics.fraunhofer import fraunhofer_mft, intensity_fft
from invglare.optics.fresnel import fresnel_phase
from invglare.optics.sampling import (
    AngularGrid,
    ApertureGrid,
    check_positive,
    check_wavelengths_nm,
)
from invglare.optics.spectral import psf_to_xyz, scaled_copies_xyz, spectral_weights, xyz_to_rgb

PROPAGATIONS = ("fraunhofer", "fresnel")
METHODS = ("auto", "fft", "mft")
SPECTRAL_METHODS = ("exact", "scaled")

#: Largest FFT the automatic method choice will pick before falling back to the MFT.
MAX_AUTO_FFT_NPIX = 4096


def _choose(name: str, value: str, valid: Sequence[str]) -> str:
    if value not in valid:
        raise ConfigError(f"{name} = {value!r} is not one of {', '.join(valid)}")
    return value


class AperturePSF(eqx.Module):
    """PSF of an aperture at a set of wavelengths, on a chosen angular output grid.

    Build one with :meth:`build`, which picks the sampling and the propagation
    method; the constructor takes every field as is.
    """

    aperture: Aperture
    grid: ApertureGrid
    output: AngularGrid
    focal_length_mm: Float[Array, ""] = eqx.field(converter=jnp.asarray)
    wavelengths_nm: Float[Array, " w"] = eqx.field(converter=jnp.asarray)
    weights_xyz: Float[Array, "w 3"] = eqx.field(converter=jnp.asarray)
    propagation: str = eqx.field(static=True, default="fraunhofer")
    method: str = eqx.field(static=True, default="mft")
    fft_npix: int = eqx.field(static=True, default=0)
    spectral: str = eqx.field(static=True, default="exact")
    reference_wavelength_nm: float = eqx.field(static=True, default=575.0)
    colourspace: str = eqx.field(static=True, default="sRGB")
    illuminant: str = eqx.field(static=True, default="E")

    @classmethod
    def build(
        cls,
        aperture: Aperture,
        *,
        focal_length_mm: float,
        wavelengths_nm: Sequence[float] | float = 550.0,
        npix: int = 512,
        pixel_scale_deg: float | None = None,
        aperture_npix: int = 256,
        window_mm: float | None = None,
        propagation: str = "fraunhofer",
        method: str = "auto",
        spectral: str = "exact",
        reference_wavelength_nm: float = 575.0,
        illuminant: str = "E",
        colourspace: str = "sRGB",
    ) -> AperturePSF:
        """Choose sampling and method for an aperture, validating every value.

        **Arguments:**

        - `focal_length_mm`: pupil-to-retina (or lens-to-sensor) distance; it sets
          the Fresnel term and the retina pixel size, not the angular PSF.
        - `wavelengths_nm`: one wavelength (monochrome PSF) or several (RGB PSF).
        - `npix`, `pixel_scale_deg`: the output grid. Without a pixel scale the FFT's
          native scale ``lambda / (fft_npix * pitch)`` is used (the fast path).
        - `aperture_npix`, `window_mm`: the aperture raster; the window defaults to
          the aperture's extent plus two pixels on each side.
        - `method`: ``"fft"``, ``"mft"`` or ``"auto"`` (FFT when the requested pixel
          scale is one the FFT produces, else the exact matrix Fourier transform).
        - `spectral`: ``"exact"`` (one transform per wavelength) or ``"scaled"``
          (copies of the `reference_wavelength_nm` PSF, Ritschel et al.).
        - `illuminant`, `colourspace`: colour-science names for the light's
          spectrum and the linear RGB space of a spectral PSF.
        """
        _choose("propagation", propagation, PROPAGATIONS)
        _choose("method", method, METHODS)
        _choose("spectral", spectral, SPECTRAL_METHODS)
        lams = np.atleast_1d(np.asarray(wavelengths_nm, dtype=float))
        check_wavelengths_nm(lams)
        check_wavelengths_nm(reference_wavelength_nm)
        check_positive("focal_length_mm", focal_length_mm, "mm")
        if int(npix) != npix or npix < 8:
            raise PhysicsRangeError(f"npix must be an integer >= 8, got {npix}")
        if int(aperture_npix) != aperture_npix or aperture_npix < 8:
            raise PhysicsRangeError(f"aperture_npix must be an integer >= 8, got {aperture_npix}")
        extent = aperture.extent_mm()
        if window_mm is None:
            window_mm = extent * aperture_npix / (aperture_npix - 4)
        check_positive("window_mm", window_mm, "mm")
        if extent > window_mm * (1 + 1e-6):
            raise PhysicsRangeError(
                f"the aperture ({extent:g} mm across) does not fit in window_mm = {window_mm:g}"
            )
        grid = ApertureGrid.from_width(int(aperture_npix), window_mm)
        pitch = window_mm / aperture_npix
        # The FFT path computes one wavelength; several need the scaled-copies approximation.
        fft_wavelength = lams[0] if lams.size == 1 else reference_wavelength_nm

        if pixel_scale_deg is None:
            if method == "mft":
                raise ConfigError("method = 'mft' needs pixel_scale_deg")
            fft_npix = max(int(npix), 2 * int(aperture_npix))
            fft_npix += fft_npix % 2
            pixel_scale_deg = math.degrees(fft_wavelength * 1e-6 / (fft_npix * pitch))
            method = "fft"
        else:
            check_positive("pixel_scale_deg", pixel_scale_deg, "deg")
            ideal = fft_wavelength * 1e-6 / (pitch * math.radians(pixel_scale_deg))
            fft_npix = round(ideal)
            fits = (
                abs(ideal - fft_npix) < 1e-6 * ideal
                and fft_npix >= aperture_npix
                and fft_npix >= npix
            )
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
        if method == "fft" and lams.size > 1 and spectral == "exact":
            raise ConfigError(
                "a spectral PSF on the FFT path needs spectral = 'scaled'; for exact "
                "per-wavelength transforms set pixel_scale_deg and method = 'mft'"
            )
        output = AngularGrid(int(npix), pixel_scale_deg)
        shortest = float(lams.min()) if spectral == "exact" else float(fft_wavelength)
        half_field = math.radians(float(output.half_field_deg))
        if method == "mft" and half_field / (shortest * 1e-6) > 0.5 / pitch:
            supported = math.degrees(0.5 / pitch * shortest * 1e-6)
            raise PhysicsRangeError(
                f"the output field reaches {float(output.half_field_deg):.4g} deg but the aperture "
                f"sampling (pitch {pitch * 1e3:.3g} um) supports only {supported:.4g} deg at "
                f"{shortest:g} nm without aliasing; raise aperture_npix or lower npix / "
                "pixel_scale_deg"
            )
        weights = spectral_weights(lams, illuminant=illuminant)
        return cls(
            aperture=aperture,
            grid=grid,
            output=output,
            focal_length_mm=focal_length_mm,
            wavelengths_nm=lams,
            weights_xyz=weights,
            propagation=propagation,
            method=method,
            fft_npix=fft_npix,
            spectral=spectral,
            reference_wavelength_nm=float(reference_wavelength_nm),
            colourspace=colourspace,
            illuminant=illuminant,
        )

    @property
    def is_spectral(self) -> bool:
        return self.wavelengths_nm.shape[0] > 1

    def transmission(self) -> Float[Array, "n n"]:
        """The rasterised aperture transmission on :attr:`grid`."""
        return self.aperture.transmission(self.grid)

    def monochrome(self, wavelength_nm) -> Float[Array, "npix npix"]:
        """Unit-energy PSF at one wavelength (on the FFT path: at the FFT's own scale)."""
        field = self.transmission()
        if self.propagation == "fresnel":
            field = field * fresnel_phase(self.grid, wavelength_nm, self.focal_length_mm)
        if self.method == "fft":
            return intensity_fft(field, self.fft_npix, self.output.npix)
        return fraunhofer_mft(field, self.grid, wavelength_nm, self.output)

    def __call__(self) -> Float[Array, "npix npix"] | Float[Array, "npix npix 3"]:
        if not self.is_spectral:
            return self.monochrome(self.wavelengths_nm[0])
        if self.spectral == "scaled":
            reference = self.monochrome(jnp.asarray(self.reference_wavelength_nm))
            xyz = scaled_copies_xyz(
                reference, self.reference_wavelength_nm, self.wavelengths_nm, self.weights_xyz
            )
        else:
            psfs = jax.vmap(self.monochrome)(self.wavelengths_nm)
            xyz = psf_to_xyz(psfs, self.weights_xyz)
        return xyz_to_rgb(xyz, self.colourspace)
