"""The PSF of a static aperture: the simplest forward model, and the base of the others.

An :class:`AperturePSF` rasterises an :class:`~invglare.aperture.Aperture`,
propagates it with a :class:`~invglare.optics.propagator.Propagator`
(Fraunhofer, or with the Fresnel term of eq. 3 of the temporal-glare paper) and
integrates over its :class:`~invglare.optics.spectral.Spectrum`, returning

* a monochrome PSF ``(npix, npix)`` for one wavelength, or
* a linear RGB PSF ``(npix, npix, 3)`` for several,

normalised as in :mod:`invglare.optics.fraunhofer` (fraction of the transmitted
power per pixel; for RGB the luminance Y carries that normalisation).
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import numpy as np
from jaxtyping import Array, Float

from invglare.aperture import Aperture
from invglare.errors import ConfigError, PhysicsRangeError
from invglare.optics.propagator import Propagator
from invglare.optics.spectral import Spectrum


def default_window_mm(extent_mm: float, aperture_npix: int) -> float:
    """An aperture window holding `extent_mm` with two empty pixels on each side."""
    return extent_mm * aperture_npix / (aperture_npix - 4)


def build_propagator(
    extent_mm: float,
    spectrum: Spectrum,
    *,
    focal_length_mm: float,
    npix: int,
    pixel_scale_deg: float | None,
    aperture_npix: int,
    window_mm: float | None,
    propagation: str,
    method: str,
) -> Propagator:
    """A propagator whose window holds an aperture of `extent_mm` and suits the spectrum."""
    if window_mm is None:
        window_mm = default_window_mm(extent_mm, aperture_npix)
    if extent_mm > window_mm * (1 + 1e-6):
        raise PhysicsRangeError(
            f"the aperture ({extent_mm:g} mm across) does not fit in window_mm = {window_mm:g}"
        )
    computed = spectrum.computed_wavelengths_nm
    if method == "fft" and spectrum.is_spectral and spectrum.spectral == "exact":
        raise ConfigError(
            "a spectral PSF on the FFT path needs spectral = 'scaled'; for exact "
            "per-wavelength transforms set pixel_scale_deg and method = 'mft'"
        )
    propagator = Propagator.build(
        window_mm=window_mm,
        focal_length_mm=focal_length_mm,
        fft_wavelength_nm=computed[0],
        shortest_wavelength_nm=min(computed),
        npix=npix,
        pixel_scale_deg=pixel_scale_deg,
        aperture_npix=aperture_npix,
        propagation=propagation,
        method=method,
    )
    if propagator.method == "fft" and len(computed) > 1:
        # "auto" chose the FFT for the first wavelength; the others need other scales.
        return build_propagator(
            extent_mm,
            spectrum,
            focal_length_mm=focal_length_mm,
            npix=npix,
            pixel_scale_deg=float(propagator.output.pixel_scale_deg),
            aperture_npix=aperture_npix,
            window_mm=window_mm,
            propagation=propagation,
            method="mft",
        )
    return propagator


class AperturePSF(eqx.Module):
    """PSF of an aperture for a spectrum, on the propagator's angular output grid.

    Build one with :meth:`build`, which picks the sampling and the method.
    """

    aperture: Aperture
    propagator: Propagator
    spectrum: Spectrum

    @classmethod
    def build(
        cls,
        aperture: Aperture,
        *,
        focal_length_mm: float,
        wavelengths_nm: Sequence[float] | float | str = 550.0,
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

        **Example:**

        ```python
        model = AperturePSF.build(Aperture((Disk(4.0),)), focal_length_mm=17.0, npix=256)
        psf = model()  # Airy pattern at 550 nm, FFT pixel scale
        ```
        """
        spectrum = Spectrum.build(
            np.atleast_1d(np.asarray(wavelengths_nm, dtype=float))
            if not isinstance(wavelengths_nm, str)
            else wavelengths_nm,
            spectral=spectral,
            reference_wavelength_nm=reference_wavelength_nm,
            illuminant=illuminant,
            colourspace=colourspace,
        )
        propagator = build_propagator(
            aperture.extent_mm(),
            spectrum,
            focal_length_mm=focal_length_mm,
            npix=npix,
            pixel_scale_deg=pixel_scale_deg,
            aperture_npix=aperture_npix,
            window_mm=window_mm,
            propagation=propagation,
            method=method,
        )
        return cls(aperture, propagator, spectrum)

    def transmission(self) -> Float[Array, "n n"]:
        """The rasterised aperture transmission on the propagator's grid."""
        return self.aperture.transmission(self.propagator.grid)

    def __call__(self) -> Float[Array, "npix npix"] | Float[Array, "npix npix 3"]:
        field = self.transmission()
        return self.spectrum.integrate(lambda lam: self.propagator(field, lam))
