"""Propagators: from an aperture field to a unit-energy PSF on a chosen output grid.

A propagator is chosen once, when a model is built, and is an object, not a string: an
abstract :class:`AbstractPropagator` with one final class per way of getting from the
aperture plane to the angular output grid. Every one of them takes a raster of the
aperture (amplitude transmission on its :attr:`~AbstractPropagator.grid`) and returns,
per output pixel, the fraction of the transmitted power landing there (the normalisation
of :mod:`invglare.optics.fraunhofer`).

| class           | `propagation`, `method` | what it does                                    |
|-----------------|-------------------------|-------------------------------------------------|
| `FraunhoferFFT` | `fraunhofer`, `fft`     | zero-padded FFT: fixed pixel scale, fastest     |
| `FraunhoferMFT` | `fraunhofer`, `mft`     | matrix Fourier transform: any scale and field   |
| `FresnelFFT`    | `fresnel`, `fft`        | eq. 3 of Ritschel et al. (quadratic phase E)    |
| `FresnelMFT`    | `fresnel`, `mft`        | the same at any output sampling                 |
| `FresnelTransfer` | `fresnel`, `transfer` | eq. 3 on the image plane by the Fresnel kernel: |
|                 |                         | alias-free at short distances (the eye's 17 mm) |

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
from invglare.optics.fourier import pad_centred
from invglare.optics.fraunhofer import fraunhofer_mft, intensity_fft
from invglare.optics.fresnel import fresnel_near_field, fresnel_phase, near_field_fft_npix

PROPAGATIONS = ("fraunhofer", "fresnel")
METHODS = ("auto", "fft", "mft", "transfer")

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
        self, field: Inexact[Array, "n n"], wavelength_nm: ArrayLike
    ) -> Float[Array, "npix npix"]:
        """Unit-energy PSF of `field` (on `grid`) at one wavelength, on `output`."""


class FraunhoferFFT(AbstractPropagator):
    """Far field by an FFT of the field zero-padded to `fft_npix`: pixels of
    ``lambda / (fft_npix * pitch)`` rad at the wavelength the model was built for."""

    fft_npix: int = eqx.field(static=True, kw_only=True)
    propagation: ClassVar[str] = "fraunhofer"
    method: ClassVar[str] = "fft"

    def __call__(self, field, wavelength_nm):
        return intensity_fft(field, self.fft_npix, self.output.npix)


class FraunhoferMFT(AbstractPropagator):
    """Far field by matrix Fourier transform: any output pixel scale and field.

    With `core_npix` (static) below the output's size, the transform covers only the
    central ``core_npix`` pixels, the raster's alias-free band, and the rest of the output
    is 0: what lies beyond is left to a closed-form term of the model (the wide-angle
    scatter of :mod:`invglare.optics.particles`).
    """

    core_npix: int | None = eqx.field(static=True, default=None, kw_only=True)
    propagation: ClassVar[str] = "fraunhofer"
    method: ClassVar[str] = "mft"

    def __call__(self, field, wavelength_nm):
        if self.core_npix is None or self.core_npix >= self.output.npix:
            return fraunhofer_mft(field, self.grid, wavelength_nm, self.output)
        core = AngularGrid(self.core_npix, self.output.pixel_scale_deg)
        return pad_centred(fraunhofer_mft(field, self.grid, wavelength_nm, core), self.output.npix)


class FresnelFFT(AbstractPropagator):
    """Eq. 3 of Ritschel et al.: the field times ``E = exp(i pi r^2 / (lambda f))``, one FFT."""

    fft_npix: int = eqx.field(static=True, kw_only=True)
    propagation: ClassVar[str] = "fresnel"
    method: ClassVar[str] = "fft"

    def __call__(self, field, wavelength_nm):
        field = field * fresnel_phase(self.grid, wavelength_nm, self.focal_length_mm)
        return intensity_fft(field, self.fft_npix, self.output.npix)


class FresnelMFT(AbstractPropagator):
    """Eq. 3 of Ritschel et al. at any output sampling (matrix Fourier transform)."""

    propagation: ClassVar[str] = "fresnel"
    method: ClassVar[str] = "mft"

    def __call__(self, field, wavelength_nm):
        field = field * fresnel_phase(self.grid, wavelength_nm, self.focal_length_mm)
        return fraunhofer_mft(field, self.grid, wavelength_nm, self.output)


class FresnelTransfer(AbstractPropagator):
    """Eq. 3 of Ritschel et al. at a short distance, on the image plane, without aliasing.

    The aperture convolved with the Fresnel kernel (:func:`~invglare.optics.fresnel.
    fresnel_near_field`): output pixels are the aperture pitch on the image plane,
    ``pitch / focal_length`` rad, the same at every wavelength. It needs the transfer
    function sampled (``fft_npix * pitch^2 >= lambda d``), which short distances make easy;
    the single-FFT form (:class:`FresnelFFT`) needs the phase ``E`` resolved instead,
    which long distances make easy.
    """

    fft_npix: int = eqx.field(static=True, kw_only=True)
    propagation: ClassVar[str] = "fresnel"
    method: ClassVar[str] = "transfer"

    def __call__(self, field, wavelength_nm):
        return fresnel_near_field(
            field, self.grid, wavelength_nm, self.focal_length_mm, self.fft_npix, self.output.npix
        )


#: (propagation, method) of the config → the final class.
PROPAGATOR_CLASSES: dict[tuple[str, str], type[AbstractPropagator]] = {
    (cls.propagation, cls.method): cls
    for cls in (FraunhoferFFT, FraunhoferMFT, FresnelFFT, FresnelMFT, FresnelTransfer)
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
    longest_wavelength_nm: float | None = None,
    beyond_band: bool = False,
) -> AbstractPropagator:
    """The propagator for a sampling, refusing ones that would alias.

    **Arguments:**

    - `window_mm`, `aperture_npix`: the aperture raster (pitch = window / npix).
    - `focal_length_mm`: pupil-to-retina / lens-to-sensor distance (Fresnel term).
    - `fft_wavelength_nm`: the wavelength an FFT is computed at (it fixes the FFT
      pixel scale ``lambda / (fft_npix * pitch)``).
    - `shortest_wavelength_nm`: the shortest wavelength an MFT will evaluate; the
      output field must stay within its alias-free band.
    - `longest_wavelength_nm`: the longest wavelength evaluated (``"transfer"`` samples
      its transfer function for it); default the larger of the two above.
    - `beyond_band`: let a Fraunhofer MFT output reach beyond the raster's alias-free
      band: the transform covers the band's pixels (`FraunhoferMFT.core_npix`) and the
      model fills the rest in closed form; otherwise such an output is refused.
    - `npix`, `pixel_scale_deg`: the output grid; without a pixel scale, the FFT's
      native one (with ``fft_npix = max(npix, 2 * aperture_npix)``).
    - `propagation`: ``"fraunhofer"`` or ``"fresnel"``.
    - `method`: ``"fft"``, ``"mft"`` or ``"auto"`` (the FFT when it produces the
      requested pixel scale exactly, else the MFT); ``"transfer"`` (Fresnel only) for the
      image-plane near field of :class:`FresnelTransfer`, whose pixels are
      ``pitch / focal_length_mm`` rad (a `pixel_scale_deg` must equal that).

    **Returns:** a :class:`FraunhoferFFT`, :class:`FraunhoferMFT`, :class:`FresnelFFT`,
    :class:`FresnelMFT` or :class:`FresnelTransfer`.

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
    if method == "transfer":
        return _transfer_propagator(
            window_mm=window_mm,
            focal_length_mm=focal_length_mm,
            longest_wavelength_nm=max(
                fft_wavelength_nm, shortest_wavelength_nm, longest_wavelength_nm or 0.0
            ),
            npix=npix,
            pixel_scale_deg=pixel_scale_deg,
            aperture_npix=aperture_npix,
            propagation=propagation,
        )
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
    core_npix = None
    if method == "mft":
        half_field = math.radians(float(output.half_field_deg))
        band = math.degrees(0.5 / pitch * shortest_wavelength_nm * 1e-6)
        if beyond_band and propagation == "fraunhofer" and float(output.half_field_deg) > band:
            # The largest centred square inside the band, of the output's parity.
            core_npix = 2 * int(band / float(output.pixel_scale_deg) * (1 + 1e-6)) + npix % 2
            core_npix = max(core_npix - (core_npix - npix) % 2, 1)
        # A relative margin: a field exactly at the band edge (the FFT's own) is fine
        # and must not be refused for a float32 rounding error.
        elif half_field / (shortest_wavelength_nm * 1e-6) > 0.5 / pitch * (1 + 1e-6):
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
    if core_npix is not None:
        return cls(
            grid=grid, output=output, focal_length_mm=focal_length_mm, core_npix=core_npix
        )
    return cls(grid=grid, output=output, focal_length_mm=focal_length_mm)


def _transfer_propagator(
    *,
    window_mm: float,
    focal_length_mm: float,
    longest_wavelength_nm: float,
    npix: int,
    pixel_scale_deg: float | None,
    aperture_npix: int,
    propagation: str,
) -> FresnelTransfer:
    """The :class:`FresnelTransfer` of a sampling (its pixel scale is the grid's, not chosen)."""
    if propagation != "fresnel":
        raise ConfigError(
            "method = 'transfer' is the Fresnel near field (propagation = 'fresnel'); the "
            "far field takes 'fft', 'mft' or 'auto'"
        )
    grid = ApertureGrid.from_width(aperture_npix, window_mm)
    native_deg = math.degrees(window_mm / aperture_npix / focal_length_mm)
    if pixel_scale_deg is not None and abs(pixel_scale_deg - native_deg) > 1e-6 * native_deg:
        raise ConfigError(
            f"method = 'transfer' puts the PSF on the image plane at the aperture pitch, "
            f"{native_deg:.6g} deg per pixel here (pitch / focal_length_mm); pixel_scale_deg = "
            f"{pixel_scale_deg:g} differs: drop it, or change window_mm / aperture_npix"
        )
    # The transfer function is sampled for the longest wavelength it meets (its phase
    # grows with lambda d).
    fft_npix = near_field_fft_npix(grid, longest_wavelength_nm, focal_length_mm, npix)
    output = AngularGrid(npix, native_deg)
    return FresnelTransfer(
        grid=grid, output=output, focal_length_mm=focal_length_mm, fft_npix=fft_npix
    )
