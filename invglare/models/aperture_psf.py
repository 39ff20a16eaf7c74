"""The PSF of a static aperture: the simplest forward model, and the base of the others.

An :class:`AperturePSF` rasterises an :class:`~invglare.aperture.Aperture`,
propagates it with a :class:`~invglare.optics.propagator.AbstractPropagator`
(Fraunhofer, or with the Fresnel term of eq. 3 of the temporal-glare paper) and
integrates over its :class:`~invglare.optics.spectral.Spectrum`, returning

* a monochrome PSF ``(npix, npix)`` for one wavelength, or
* a linear RGB PSF ``(npix, npix, 3)`` for several,

normalised as in :mod:`invglare.optics.fraunhofer` (fraction of the power through the
aperture per pixel; for RGB the luminance Y carries that normalisation). That power is the
area of a lone disk, ellipse, polygon or capsule in closed form
(:meth:`~invglare.aperture.Aperture.open_area_mm2`), and the raster's transmission
``sum |t| pitch^2`` for any other aperture.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar, Unpack

import numpy as np
from jaxtyping import Array, ArrayLike, Float

from invglare.aperture import Aperture, shape_to_config
from invglare.models.base import AbstractShiftInvariantModel, check_no_state, light_angle
from invglare.models.raster import (
    AbstractRasterModel,
    RasterSampling,
    build_propagator,
    prepared_for,
    raster_header,
)
from invglare.optics.propagator import AbstractPropagator
from invglare.optics.spectral import Spectrum


class AperturePSF(AbstractRasterModel, AbstractShiftInvariantModel):
    """PSF of an aperture for a spectrum, on the propagator's angular output grid.

    Build one with :meth:`build`, which picks the sampling and the method. The PSF does
    not depend on the light's direction (shift invariant): a light angle passed to a call
    is checked and otherwise ignored.
    """

    aperture: Aperture
    propagator: AbstractPropagator
    spectrum: Spectrum
    centre: ClassVar[str] = "light"
    animated: ClassVar[bool] = False

    @classmethod
    def build(
        cls,
        aperture: Aperture,
        *,
        focal_length_mm: float,
        wavelengths_nm: Sequence[float] | float | str = 550.0,
        method: str = "auto",
        spectral: str = "exact",
        reference_wavelength_nm: float = 575.0,
        illuminant: str = "E",
        colourspace: str = "sRGB",
        **raster: Unpack[RasterSampling],
    ) -> AperturePSF:
        """Choose sampling and method for an aperture, validating every value.

        **Arguments:**

        - `focal_length_mm`: pupil-to-retina (or lens-to-sensor) distance; it sets
          the Fresnel term and the retina pixel size, not the angular PSF.
        - `wavelengths_nm`: one wavelength (monochrome PSF) or several (RGB PSF).
        - `npix`, `pixel_scale_deg`: the output grid (default 512 pixels). Without a pixel
          scale the FFT's native scale ``lambda / (fft_npix * pitch)`` is used (the fast path).
        - `aperture_npix`, `window_mm`: the aperture raster (default 256 pixels); the window
          defaults to the aperture's extent plus two pixels on each side.
        - `propagation`: ``"fraunhofer"`` (default) or ``"fresnel"`` (the Fresnel term of the
          temporal-glare paper's eq. 3).
        - `method`: ``"fft"``, ``"mft"`` or ``"auto"`` (FFT when the requested pixel
          scale is one the FFT produces, else the exact matrix Fourier transform);
          ``"quad"`` (the raster's quads in closed form: any sampling, no aliasing, the
          near field without chirp sampling) or ``"polygon"`` (the shapes' exact
          transforms, no raster); see :mod:`invglare.optics.quad`.
        - `method_options`: the quad or polygon options (``[model.quad]`` /
          ``[model.polygon]``).
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
            aperture.extent_mm(), spectrum, focal_length_mm=focal_length_mm, method=method, **raster
        )
        propagator = prepared_for(propagator, aperture, aperture.transmission(propagator.grid))
        return cls(aperture, propagator, spectrum)

    def transmission(self) -> Float[Array, "n n"]:
        """The rasterised aperture transmission on the propagator's grid."""
        return self.aperture.transmission(self.propagator.grid)

    def psf(self) -> Float[Array, "npix npix"] | Float[Array, "npix npix 3"]:
        """The PSF: mono ``(npix, npix)`` for one wavelength, linear RGB ``(npix, npix, 3)``."""
        takes_shapes = self.propagator.takes == "shapes"
        field = self.aperture if takes_shapes else self.transmission()
        area = self.aperture.open_area_mm2()
        return self.spectrum.integrate(lambda lam: self.propagator(field, lam, open_area_mm2=area))

    # ------------------------------------------------------------------ the model interface

    def __call__(
        self, light_angle_deg: Float[ArrayLike, " 2"] | None = None, *, state: Any = None
    ) -> Float[Array, "npix npix"] | Float[Array, "npix npix 3"]:
        """The PSF (the same for every light direction; see :meth:`psf`)."""
        light_angle(light_angle_deg)
        check_no_state(self, state)
        return self.psf()

    def spot_raster(self) -> Float[Array, "n n"]:
        return self.transmission()

    def header(self) -> dict[str, Any]:
        return raster_header(self)

    def sized_for(self, others) -> AperturePSF:
        return self  # analytic shapes: no static raster structure to size

    def to_config(self) -> dict[str, Any]:
        return {
            "model": {
                "kind": "aperture",
                **propagator_table(self.propagator),
                "shapes": [shape_to_config(s) for s in self.aperture.shapes],
            },
            **output_and_spectrum_tables(self.propagator, self.spectrum),
        }


def propagator_table(prop: AbstractPropagator) -> dict[str, Any]:
    """The `[model]` keys of a propagator's choices (and its method's own table)."""
    table = {
        "focal_length_mm": float(prop.focal_length_mm),
        "propagation": prop.propagation,
        "aperture_npix": prop.grid.npix,
        "window_mm": float(prop.grid.width_mm),
        "method": prop.method,
    }
    options = prop.options()
    if options:
        table[prop.method] = options
    return table


def output_and_spectrum_tables(prop: AbstractPropagator, spec: Spectrum) -> dict[str, Any]:
    """The `[output]` and `[spectrum]` tables of a raster model (every choice explicit)."""
    return {
        "output": {
            "npix": prop.output.npix,
            "pixel_scale_deg": float(prop.output.pixel_scale_deg),
        },
        "spectrum": {
            "wavelengths_nm": [float(w) for w in np.asarray(spec.wavelengths_nm).reshape(-1)],
            "spectral": spec.spectral,
            "reference_wavelength_nm": spec.reference_wavelength_nm,
            "illuminant": spec.illuminant,
            "colourspace": spec.colourspace,
        },
    }
