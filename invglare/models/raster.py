"""What every raster model shares: its propagator and spectrum, its central spot, its header.

A raster model rasterises an aperture on its propagator's grid and propagates it for each
wavelength of its spectrum (:class:`AbstractRasterModel`); :func:`build_propagator` makes
the sampling choices they all make the same way.
"""

# No `from __future__ import annotations` here: equinox reads the AbstractVar
# annotations as objects when the class is created.
import abc
import math
from collections.abc import Mapping
from typing import Any, TypedDict

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from invglare._core.grids import AngularGrid, ApertureGrid
from invglare.errors import ConfigError, PhysicsRangeError
from invglare.models.base import AbstractGlareModel, wavelength_tuple
from invglare.optics.propagator import AbstractPropagator, make_propagator
from invglare.optics.spectral import Spectrum

#: What every PSF of a propagator holds per pixel (for file headers).
PSF_NORMALISATION = (
    "fraction of the power through the aperture per pixel (Y sums to just under 1 over the "
    "full plane)"
)

#: First zero of the Airy pattern, in units of wavelength / diameter (rad).
AIRY_FIRST_ZERO = 1.2196698912665045


def default_window_mm(extent_mm: float, aperture_npix: int) -> float:
    """An aperture window holding `extent_mm` with two empty pixels on each side."""
    return extent_mm * aperture_npix / (aperture_npix - 4)


class RasterSampling(TypedDict, total=False):
    """The sampling choices a raster model's `build` hands on to :func:`build_propagator`
    as they are (each optional: left out, it takes that function's default)."""

    npix: int
    pixel_scale_deg: float | None
    aperture_npix: int
    window_mm: float | None
    propagation: str
    method_options: Mapping[str, Any] | None


def build_propagator(
    extent_mm: float,
    spectrum: Spectrum,
    *,
    focal_length_mm: float,
    npix: int = 512,
    pixel_scale_deg: float | None = None,
    aperture_npix: int = 256,
    window_mm: float | None = None,
    propagation: str = "fraunhofer",
    method: str = "auto",
    method_options: Mapping[str, Any] | None = None,
    beyond_band: bool = False,
) -> AbstractPropagator:
    """A propagator whose window holds an aperture of `extent_mm` and suits the spectrum.

    A quad or polygon propagator still has to be :meth:`~invglare.optics.propagator.
    AbstractPropagator.prepared` for the model's aperture (see :func:`prepared_for`).
    `beyond_band`: see :func:`~invglare.optics.propagator.make_propagator`.

    The defaults are the static models' (aperture, eye, camera): their `build` hands on the
    :class:`RasterSampling` it is given.
    """
    if isinstance(aperture_npix, bool) or not isinstance(aperture_npix, int) or aperture_npix < 8:
        raise PhysicsRangeError(f"aperture_npix must be an integer >= 8, got {aperture_npix}")
    if window_mm is None:
        window_mm = default_window_mm(extent_mm, aperture_npix)
    if extent_mm > window_mm * (1 + 1e-6):
        raise PhysicsRangeError(
            f"the aperture ({extent_mm:g} mm across) does not fit in window_mm = {window_mm:g}"
        )
    computed = spectrum.computed_wavelengths_nm
    if spectrum.spectral == "near_field_heuristic" and propagation != "fresnel":
        raise ConfigError(
            "spectral = 'near_field_heuristic' approximates near-field (propagation = "
            f"'fresnel') spectra; with propagation = {propagation!r} use spectral = 'scaled' "
            "(exact in the far field) or 'exact'"
        )
    if method == "fft" and spectrum.is_spectral and spectrum.spectral == "exact":
        raise ConfigError(
            "a spectral PSF on the FFT path needs spectral = 'scaled'; for exact "
            "per-wavelength transforms set pixel_scale_deg and method = 'mft'"
        )
    propagator = make_propagator(
        window_mm=window_mm,
        focal_length_mm=focal_length_mm,
        fft_wavelength_nm=computed[0],
        shortest_wavelength_nm=min(computed),
        npix=npix,
        pixel_scale_deg=pixel_scale_deg,
        aperture_npix=aperture_npix,
        propagation=propagation,
        method=method,
        method_options=method_options,
        wavelengths_nm=tuple(computed),
        longest_wavelength_nm=max(computed),
        beyond_band=beyond_band,
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
            beyond_band=beyond_band,
        )
    return propagator


def prepared_for(propagator: AbstractPropagator, aperture, raster) -> AbstractPropagator:
    """The propagator prepared for a model's aperture: given the shapes when it takes them
    (the polygon method), else the raster (the quad method decides its quadtree on it)."""
    return propagator.prepared(aperture if propagator.takes == "shapes" else raster)


def central_spot_radius_px(
    transmission: Float[Array, "n n"],
    grid: ApertureGrid,
    longest_wavelength_nm: Float[Array, ""] | float,
    output: AngularGrid,
) -> Float[Array, ""]:
    """First Airy zero (output pixels) of a disk with the aperture's transmitting area.

    ``1.2197 * lambda / D_eq`` with ``D_eq`` the diameter of the disk of area
    ``sum(t) * pitch²``, divided by the output pixel scale.
    """
    area_mm2 = jnp.sum(transmission) * grid.pitch_mm**2
    d_eq_mm = 2.0 * jnp.sqrt(area_mm2 / math.pi)
    lam_mm = jnp.asarray(longest_wavelength_nm) * 1e-6
    return AIRY_FIRST_ZERO * lam_mm / d_eq_mm / output.pixel_scale_rad


class AbstractRasterModel(AbstractGlareModel):
    """A model that rasterises an aperture on its propagator's grid, for its spectrum.

    Its image is on the propagator's output grid, at the spectrum's wavelengths; its
    central spot is that of a disk with the area :meth:`spot_raster` transmits.
    """

    propagator: eqx.AbstractVar[AbstractPropagator]
    spectrum: eqx.AbstractVar[Spectrum]

    @abc.abstractmethod
    def spot_raster(self) -> Float[Array, "n n"]:
        """The transmission whose area sets the central spot (the pupil, at rest)."""

    @property
    def pixel_scale_deg(self) -> Float[Array, ""]:
        return self.propagator.output.pixel_scale_deg

    @property
    def wavelengths_nm(self) -> tuple[float, ...]:
        return wavelength_tuple(self.spectrum.wavelengths_nm)

    def central_spot_radius_px(self) -> Float[Array, ""]:
        """Radius (output pixels) of the central spot: first Airy zero at the reddest wavelength.

        ``1.2197 * lambda_max / D_eq`` with ``D_eq`` the diameter of the disk with the
        area :meth:`spot_raster` transmits (``sum(P) * pitch²``), divided by the output
        pixel scale. Meant for splitting off the central spot before tone mapping
        (:func:`invglare.render.kakimoto_glare_layers`); ``float()`` it there.
        """
        return central_spot_radius_px(
            self.spot_raster(),
            self.propagator.grid,
            jnp.max(self.spectrum.wavelengths_nm),
            self.propagator.output,
        )

    def core_radius_px(self) -> float:
        return float(self.central_spot_radius_px())


def raster_header(model: "AbstractRasterModel", normalisation: str = PSF_NORMALISATION) -> dict:
    """The file-header values of a raster model's image."""
    return {"psfNormalisation": normalisation, "propagationMethod": model.propagator.method}
