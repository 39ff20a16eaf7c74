"""Propagators: from an aperture field to a unit-energy PSF on a chosen output grid.

A propagator is chosen once, when a model is built, and is an object, not a string: an
abstract :class:`AbstractPropagator` with one final class per way of getting from the
aperture plane to the angular output grid. Every one of them takes a raster of the
aperture (amplitude transmission on its :attr:`~AbstractPropagator.grid`) and returns,
per output pixel, the fraction of the power through the aperture landing there (the
normalisation of :mod:`invglare.optics.fraunhofer`: a closed-form area passed as
`open_area_mm2`, else the raster's own transmission).

| class           | `propagation`, `method` | what it does                                    |
|-----------------|-------------------------|-------------------------------------------------|
| `FraunhoferFFT` | `fraunhofer`, `fft`     | zero-padded FFT: fixed pixel scale, fastest     |
| `FraunhoferMFT` | `fraunhofer`, `mft`     | matrix Fourier transform: any scale and field   |
| `FresnelFFT`    | `fresnel`, `fft`        | eq. 3 of Ritschel et al. (quadratic phase E)    |
| `FresnelMFT`    | `fresnel`, `mft`        | the same at any output sampling                 |

:func:`make_propagator` turns the config's strings into one of them, checking that the
sampling cannot alias. A propagation that does not start from a raster (an analytic
transform of vector shapes) or that crosses several planes (a stack of thin layers) is a
new final subclass: it has the `grid`, `output` and `focal_length_mm` of every
propagator and implements ``__call__(field, wavelength_nm)``; models call nothing else
(see `CONTRIBUTING.md`, "Adding a propagation").
"""

# No `from __future__ import annotations` here: equinox reads the AbstractVar and
# AbstractClassVar annotations as objects when the class is created.
import abc
import math
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Inexact

from invglare._core.checks import check_positive, choose
from invglare._core.grids import AngularGrid, ApertureGrid
from invglare.errors import ConfigError, PhysicsRangeError
from invglare.optics.fraunhofer import fraunhofer_mft, intensity_fft, transmitted_power
from invglare.optics.fresnel import fresnel_phase

PROPAGATIONS = ("fraunhofer", "fresnel")
METHODS = ("auto", "fft", "mft")

#: Largest FFT the automatic method choice will pick before falling back to the MFT.
MAX_AUTO_FFT_NPIX = 4096


class AbstractPropagator(eqx.Module):
    """Aperture field → unit-energy PSF (see :mod:`invglare.optics.fraunhofer`).

    **Fields every propagator has:**

    - `grid`: the aperture raster the field is sampled on.
    - `output`: the angular output grid of the PSF.
    - `focal_length_mm`: pupil-to-retina / lens-to-sensor distance (it sets the Fresnel
      term and the retina pixel size, not the angular PSF of a Fraunhofer propagator).

    **Class variables:** `propagation` and `method`, the config strings it is written as.
    """

    grid: ApertureGrid
    output: AngularGrid
    focal_length_mm: Float[Array, ""] = eqx.field(converter=jnp.asarray)
    propagation: eqx.AbstractClassVar[str]
    method: eqx.AbstractClassVar[str]

    @abc.abstractmethod
    def __call__(
        self,
        field: Inexact[Array, "n n"],
        wavelength_nm: ArrayLike,
        *,
        open_area_mm2: ArrayLike | None = None,
    ) -> Float[Array, "npix npix"]:
        """PSF of `field` (on `grid`) at one wavelength, on `output`, per unit power.

        `open_area_mm2`: the aperture's area in closed form where the caller knows it;
        None measures the power through the aperture on the raster, ``sum |t| pitch^2``.
        """


class FraunhoferFFT(AbstractPropagator):
    """Far field by an FFT of the field zero-padded to `fft_npix`: pixels of
    ``lambda / (fft_npix * pitch)`` rad at the wavelength the model was built for."""

    fft_npix: int = eqx.field(static=True, kw_only=True)
    propagation: ClassVar[str] = "fraunhofer"
    method: ClassVar[str] = "fft"

    def __call__(self, field, wavelength_nm, *, open_area_mm2=None):
        area_px = None if open_area_mm2 is None else open_area_mm2 / self.grid.pitch_mm**2
        return intensity_fft(field, self.fft_npix, self.output.npix, open_area_px=area_px)


class FraunhoferMFT(AbstractPropagator):
    """Far field by matrix Fourier transform: any output pixel scale and field."""

    propagation: ClassVar[str] = "fraunhofer"
    method: ClassVar[str] = "mft"

    def __call__(self, field, wavelength_nm, *, open_area_mm2=None):
        return fraunhofer_mft(
            field, self.grid, wavelength_nm, self.output, open_area_mm2=open_area_mm2
        )


class FresnelFFT(AbstractPropagator):
    """Eq. 3 of Ritschel et al.: the field times ``E = exp(i pi r^2 / (lambda f))``, one FFT."""

    fft_npix: int = eqx.field(static=True, kw_only=True)
    propagation: ClassVar[str] = "fresnel"
    method: ClassVar[str] = "fft"

    def __call__(self, field, wavelength_nm, *, open_area_mm2=None):
        # The phase leaves the power through the aperture as it is: measured before it.
        if open_area_mm2 is None:
            open_area_mm2 = transmitted_power(field, self.grid.pitch_mm)
        field = field * fresnel_phase(self.grid, wavelength_nm, self.focal_length_mm)
        area_px = open_area_mm2 / self.grid.pitch_mm**2
        return intensity_fft(field, self.fft_npix, self.output.npix, open_area_px=area_px)


class FresnelMFT(AbstractPropagator):
    """Eq. 3 of Ritschel et al. at any output sampling (matrix Fourier transform)."""

    propagation: ClassVar[str] = "fresnel"
    method: ClassVar[str] = "mft"

    def __call__(self, field, wavelength_nm, *, open_area_mm2=None):
        if open_area_mm2 is None:
            open_area_mm2 = transmitted_power(field, self.grid.pitch_mm)
        field = field * fresnel_phase(self.grid, wavelength_nm, self.focal_length_mm)
        return fraunhofer_mft(
            field, self.grid, wavelength_nm, self.output, open_area_mm2=open_area_mm2
        )


#: (propagation, method) of the config → the final class.
PROPAGATOR_CLASSES: dict[tuple[str, str], type[AbstractPropagator]] = {
    (cls.propagation, cls.method): cls
    for cls in (FraunhoferFFT, FraunhoferMFT, FresnelFFT, FresnelMFT)
}


def _check_npix(name: str, value: int, minimum: int) -> int:
    if isinstance(value, bool) or int(value) != value or value < minimum:
        raise PhysicsRangeError(f"{name} must be an integer >= {minimum}, got {value}")
    return int(value)


def make_propagator(
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
) -> AbstractPropagator:
    """The propagator for a sampling, refusing ones that would alias.

    **Arguments:**

    - `window_mm`, `aperture_npix`: the aperture raster (pitch = window / npix).
    - `focal_length_mm`: pupil-to-retina / lens-to-sensor distance (Fresnel term).
    - `fft_wavelength_nm`: the wavelength an FFT is computed at (it fixes the FFT
      pixel scale ``lambda / (fft_npix * pitch)``).
    - `shortest_wavelength_nm`: the shortest wavelength an MFT will evaluate; the
      output field must stay within its alias-free band.
    - `npix`, `pixel_scale_deg`: the output grid; without a pixel scale, the FFT's
      native one (with ``fft_npix = max(npix, 2 * aperture_npix)``).
    - `propagation`: ``"fraunhofer"`` or ``"fresnel"``.
    - `method`: ``"fft"``, ``"mft"`` or ``"auto"`` (the FFT when it produces the
      requested pixel scale exactly, else the MFT).

    **Returns:** a :class:`FraunhoferFFT`, :class:`FraunhoferMFT`, :class:`FresnelFFT` or
    :class:`FresnelMFT`.

    **Example:**

    ```python
    prop = make_propagator(window_mm=4.2, focal_length_mm=17.0, fft_wavelength_nm=550.0,
                           shortest_wavelength_nm=550.0, npix=256)
    psf = prop(aperture_raster, 550.0)
    ```
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
    cls = PROPAGATOR_CLASSES[(propagation, method)]
    grid = ApertureGrid.from_width(aperture_npix, window_mm)
    if method == "fft":
        return cls(grid=grid, output=output, focal_length_mm=focal_length_mm, fft_npix=fft_npix)
    return cls(grid=grid, output=output, focal_length_mm=focal_length_mm)
