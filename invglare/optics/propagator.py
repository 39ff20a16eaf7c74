"""Propagators: from an aperture field to a PSF per unit power through it, on a chosen grid.

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
| `QuadFraunhofer`| `fraunhofer`, `quad`    | closed-form transform of the raster's quads     |
| `QuadFresnel`   | `fresnel`, `quad`       | Fresnel integrals per quad: no chirp sampling   |
| `PolygonFraunhofer` | `fraunhofer`, `polygon` | exact transforms of the shapes themselves   |
| `FresnelTransfer` | `fresnel`, `transfer` | eq. 3 on the image plane by the Fresnel kernel: |
|                 |                         | alias-free at short distances (the eye's 17 mm) |

The quad and polygon methods (:mod:`invglare.optics.quad`, Scandolo, Lee & Eisemann 2018)
decide a structure on concrete values (the quadtree of a raster; which shapes overlap)
before any call: :meth:`AbstractPropagator.prepared` returns a propagator ready for a
model's aperture, and models call it when they are built. `takes` says what a call
expects: ``"raster"`` (the aperture's transmission on `grid`) or ``"shapes"`` (the
:class:`~invglare.aperture.Aperture` itself, for the polygon method).

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
import dataclasses
import math
from collections.abc import Mapping
from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Inexact

from invglare._core.checks import check_positive, choose, is_concrete
from invglare._core.grids import AngularGrid, ApertureGrid
from invglare.errors import ConfigError, PhysicsRangeError
from invglare.optics.fourier import pad_centred
from invglare.optics.fraunhofer import fraunhofer_mft, intensity_fft, transmitted_power
from invglare.optics.fresnel import fresnel_near_field, fresnel_phase, near_field_fft_npix
from invglare.optics.quad import prepare
from invglare.optics.quad.farfield import quad_far_field
from invglare.optics.quad.nearfield import fresnel_kernel, lattice_ratio, quad_near_field
from invglare.optics.quad.options import (
    PolygonOptions,
    QuadOptions,
    check_representable,
    step_px,
)
from invglare.optics.quad.plan import QuadPlan
from invglare.optics.quad.transform import box_kernel, unfold

PROPAGATIONS = ("fraunhofer", "fresnel")
METHODS = ("auto", "fft", "mft", "transfer", "quad", "polygon")
#: The methods that take options (a ``[model.<method>]`` table).
METHOD_OPTIONS = {"quad": QuadOptions, "polygon": PolygonOptions}

#: Largest FFT the automatic method choice will pick before falling back to the MFT.
MAX_AUTO_FFT_NPIX = 4096


class AbstractPropagator(eqx.Module):
    """Aperture field → PSF per unit power through it (see :mod:`invglare.optics.fraunhofer`).

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
    takes: eqx.AbstractClassVar[str]

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

    @abc.abstractmethod
    def prepared(self, field) -> "AbstractPropagator":
        """A copy ready for `field` (concrete: a raster, or an Aperture when `takes` is
        ``"shapes"``); the discrete transforms need nothing and return themselves."""

    @abc.abstractmethod
    def options(self) -> dict[str, Any]:
        """The method's own config keys (the ``[model.<method>]`` table), or ``{}``."""


class AbstractDiscretePropagator(AbstractPropagator):
    """A discrete transform of the raster (FFT, MFT, transfer function): nothing to decide
    on a concrete field beforehand and no options of its own."""

    takes: ClassVar[str] = "raster"

    def prepared(self, field):
        return self

    def options(self):
        return {}


class FraunhoferFFT(AbstractDiscretePropagator):
    """Far field by an FFT of the field zero-padded to `fft_npix`: pixels of
    ``lambda / (fft_npix * pitch)`` rad at the wavelength the model was built for."""

    fft_npix: int = eqx.field(static=True, kw_only=True)
    propagation: ClassVar[str] = "fraunhofer"
    method: ClassVar[str] = "fft"

    def __call__(self, field, wavelength_nm, *, open_area_mm2=None):
        area_px = _area_px(open_area_mm2, self.grid)
        return intensity_fft(field, self.fft_npix, self.output.npix, open_area_px=area_px)


class FraunhoferMFT(AbstractDiscretePropagator):
    """Far field by matrix Fourier transform: any output pixel scale and field.

    With `core_npix` (static) below the output's size, the transform covers only the
    central ``core_npix`` pixels, the raster's alias-free band, and the rest of the output
    is 0: what lies beyond is left to a closed-form term of the model (the wide-angle
    scatter of :mod:`invglare.optics.particles`).
    """

    core_npix: int | None = eqx.field(static=True, default=None, kw_only=True)
    propagation: ClassVar[str] = "fraunhofer"
    method: ClassVar[str] = "mft"

    def __call__(self, field, wavelength_nm, *, open_area_mm2=None):
        if self.core_npix is None or self.core_npix >= self.output.npix:
            return fraunhofer_mft(
                field, self.grid, wavelength_nm, self.output, open_area_mm2=open_area_mm2
            )
        core = AngularGrid(self.core_npix, self.output.pixel_scale_deg)
        psf = fraunhofer_mft(field, self.grid, wavelength_nm, core, open_area_mm2=open_area_mm2)
        return pad_centred(psf, self.output.npix)


class FresnelFFT(AbstractDiscretePropagator):
    """Eq. 3 of Ritschel et al.: the field times ``E = exp(i pi r^2 / (lambda f))``, one FFT."""

    fft_npix: int = eqx.field(static=True, kw_only=True)
    propagation: ClassVar[str] = "fresnel"
    method: ClassVar[str] = "fft"

    def __call__(self, field, wavelength_nm, *, open_area_mm2=None):
        field, open_area_mm2 = _chirped(self, field, wavelength_nm, open_area_mm2)
        area_px = open_area_mm2 / self.grid.pitch_mm**2
        return intensity_fft(field, self.fft_npix, self.output.npix, open_area_px=area_px)


class FresnelMFT(AbstractDiscretePropagator):
    """Eq. 3 of Ritschel et al. at any output sampling (matrix Fourier transform)."""

    propagation: ClassVar[str] = "fresnel"
    method: ClassVar[str] = "mft"

    def __call__(self, field, wavelength_nm, *, open_area_mm2=None):
        field, open_area_mm2 = _chirped(self, field, wavelength_nm, open_area_mm2)
        return fraunhofer_mft(
            field, self.grid, wavelength_nm, self.output, open_area_mm2=open_area_mm2
        )


def _chirped(prop: AbstractPropagator, field, wavelength_nm, open_area_mm2):
    """`field` times the Fresnel phase ``E`` over `prop`'s focal length, and the power through
    the aperture: ``E`` leaves it as it is, so it is measured before (unless given)."""
    if open_area_mm2 is None:
        open_area_mm2 = transmitted_power(field, prop.grid.pitch_mm)
    return field * fresnel_phase(prop.grid, wavelength_nm, prop.focal_length_mm), open_area_mm2


class AbstractQuadPropagator(AbstractPropagator):
    """The raster's quads in closed form (Scandolo et al.): `plan` (the quadtree, decided on
    a concrete raster by :meth:`prepared`) and `tiles` (culling) are static. A final
    subclass supplies the transform (:meth:`_psf`) and its culling (:meth:`_tiles`)."""

    quad: QuadOptions = eqx.field(static=True, kw_only=True)
    wavelengths_nm: tuple[float, ...] = eqx.field(static=True, kw_only=True)
    plan: QuadPlan | None = eqx.field(static=True, default=None, kw_only=True)
    tiles: tuple | None = eqx.field(static=True, default=None, kw_only=True)
    method: ClassVar[str] = "quad"
    takes: ClassVar[str] = "raster"

    @abc.abstractmethod
    def _psf(self, plan, field, step, wavelength_nm, tiles, power_px):
        """The PSF of the checked raster `field` at one wavelength (`step`: its output
        pixel in cycles per raster pixel)."""

    @abc.abstractmethod
    def _tiles(self, plan, raster, steps) -> tuple | None:
        """The culled tiles for the model's wavelengths (`steps`, one each)."""

    def __call__(self, field, wavelength_nm, *, open_area_mm2=None):
        prop = self if self.plan is not None else self.prepared(field)
        field = prepare.checked_raster(prop.plan, field, self.method)
        step = step_px(self.grid, self.output, wavelength_nm)
        return self._psf(
            prop.plan, field, step, wavelength_nm, prepare.as_tiles(prop.tiles),
            _area_px(open_area_mm2, self.grid),
        )  # fmt: skip

    def prepared(self, field):
        raster = prepare.concrete_raster(field, self.method)
        plan = prepare.quad_plan(raster, self.quad)
        steps = tuple(float(step_px(self.grid, self.output, w)) for w in self.wavelengths_nm)
        return dataclasses.replace(self, plan=plan, tiles=self._tiles(plan, raster, steps))

    def options(self):
        return self.quad.to_dict()


class QuadFraunhofer(AbstractQuadPropagator):
    """Far field of the raster's quads in closed form (Scandolo et al., sec. 4.1-4.3).

    The raster is read as a piecewise-constant function: any output pixel scale and field,
    no padding, no aliasing; it equals the MFT of the raster times the pixel's transfer
    function ``sinc(f_x p) sinc(f_y p)``.
    """

    propagation: ClassVar[str] = "fraunhofer"

    def _psf(self, plan, field, step, wavelength_nm, tiles, power_px):
        return quad_far_field(plan, field, step, self.output.npix, tiles, power_px=power_px)

    def _tiles(self, plan, raster, steps):
        return prepare.quad_tiles(
            plan, raster, self.quad, box_kernel, self.output.npix, steps,
            (None,) * len(steps), far=True,
        )  # fmt: skip


class QuadFresnel(AbstractQuadPropagator):
    """Near field (eq. 3 of Ritschel et al.; eq. 4 of Scandolo et al.) of the raster's quads,
    each by closed-form Fresnel integrals (sec. 4.5): no chirp to sample, so no aliasing at
    any distance and no minimum raster size. `focal_length_mm` is the distance."""

    #: ``step / alpha`` as a fraction where it is one (the lattice table of
    #: :mod:`invglare.optics.quad.nearfield`), found by :meth:`prepared`; None: none.
    ratio: float | None = eqx.field(static=True, default=None, kw_only=True)
    propagation: ClassVar[str] = "fresnel"

    def alpha(self, wavelength_nm):
        """The chirp in raster pixels, ``pitch^2 / (lambda d)``."""
        return self.grid.pitch_mm**2 / (jnp.asarray(wavelength_nm) * 1e-6 * self.focal_length_mm)

    def prepared(self, field):
        # step / alpha = dtheta d / pitch: the output pixel at the distance in raster
        # pixels, the same at every wavelength.
        ratio = (
            float(self.output.pixel_scale_rad)
            * float(self.focal_length_mm)
            / float(self.grid.pitch_mm)
        )
        return dataclasses.replace(super().prepared(field), ratio=lattice_ratio(ratio))

    def _psf(self, plan, field, step, wavelength_nm, tiles, power_px):
        return quad_near_field(
            plan, field, step, self.alpha(wavelength_nm), self.output.npix, tiles,
            power_px=power_px, ratio=self.ratio,
        )  # fmt: skip

    def _tiles(self, plan, raster, steps):
        alphas = tuple(self.alpha(w) for w in self.wavelengths_nm)
        return prepare.quad_tiles(
            plan, raster, self.quad, fresnel_kernel, self.output.npix, steps, alphas,
            far=False,
        )  # fmt: skip


class PolygonFraunhofer(AbstractPropagator):
    """Far field of the aperture's shapes themselves: exact polygon and ellipse transforms
    (Lee & Mittra 1983), differentiable in every vertex, no raster (except the overlaps of
    shapes, see :mod:`invglare.optics.quad.outline`). A call takes the
    :class:`~invglare.aperture.Aperture` (`takes` is ``"shapes"``)."""

    polygon: PolygonOptions = eqx.field(static=True, kw_only=True)
    wavelengths_nm: tuple[float, ...] = eqx.field(static=True, kw_only=True)
    series_at: tuple | None = eqx.field(static=True, default=None, kw_only=True)
    overlap: QuadPlan | None = eqx.field(static=True, default=None, kw_only=True)
    propagation: ClassVar[str] = "fraunhofer"
    method: ClassVar[str] = "polygon"
    takes: ClassVar[str] = "shapes"

    def __call__(self, field, wavelength_nm, *, open_area_mm2=None):
        prop = self if self.series_at is not None else self.prepared(field)
        width = self.grid.width_mm
        pieces = prepare.aperture_pieces_checked(field, width, self.polygon.arc_segments)
        fy, fx = prepare.half_plane_freqs(self.output, wavelength_nm)
        rows, cols = (np.asarray(a, int) for a in prop.series_at)
        total = prepare.pieces_transform(pieces, fy, fx, (rows, cols))
        if prop.overlap is not None:
            residue = prepare.checked_raster(
                prop.overlap, prepare.overlap_residue(field, self.grid), self.method
            )
            step = step_px(self.grid, self.output, wavelength_nm)
            extra = prepare.residue_half_plane(prop.overlap, residue, step, self.output.npix)
            total = total + extra * self.grid.pitch_mm**2
        # Per unit power through the aperture: a closed-form area when given, else the
        # transform's own F(0), the open area of the shapes (overlaps counted once).
        area = jnp.real(total[0, self.output.npix // 2]) if open_area_mm2 is None else open_area_mm2
        area = jnp.maximum(area, 1e-30)
        scale = (self.output.pixel_scale_rad / (jnp.asarray(wavelength_nm) * 1e-6)) ** 2
        block = (total.real**2 + total.imag**2) * (scale / area)
        h = self.output.npix // 2
        return unfold(self.output.npix, block[:, h:], block[:, h::-1])

    def prepared(self, field):
        width = self.grid.width_mm
        pieces = prepare.aperture_pieces_checked(field, width, self.polygon.arc_segments)
        for piece in pieces:
            arrays = (piece.vertices, piece.centre, piece.semi_axes)
            if not all(a is None or is_concrete(a) for a in arrays):
                raise ConfigError(
                    "method = 'polygon' decides which shapes overlap on concrete shapes; "
                    "prepare the propagator outside jit with propagator.prepared(aperture)"
                )
        series = prepare.polygon_series_points(pieces, self.output, max(self.wavelengths_nm))
        overlap = prepare.overlap_plan(field, self.grid, self.polygon)
        return dataclasses.replace(self, series_at=series, overlap=overlap)

    def options(self):
        return self.polygon.to_dict()


def _area_px(open_area_mm2: ArrayLike | None, grid: ApertureGrid) -> Float[Array, ""] | None:
    """A closed-form area in aperture pixels (None stays None: measured on the raster)."""
    return None if open_area_mm2 is None else jnp.asarray(open_area_mm2) / grid.pitch_mm**2


class FresnelTransfer(AbstractDiscretePropagator):
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

    def __call__(self, field, wavelength_nm, *, open_area_mm2=None):
        return fresnel_near_field(
            field, self.grid, wavelength_nm, self.focal_length_mm, self.fft_npix,
            self.output.npix, open_area_mm2=open_area_mm2,
        )  # fmt: skip


#: (propagation, method) of the config → the final class.
PROPAGATOR_CLASSES: dict[tuple[str, str], type[AbstractPropagator]] = {
    (cls.propagation, cls.method): cls
    for cls in (
        FraunhoferFFT, FraunhoferMFT, FresnelFFT, FresnelMFT, QuadFraunhofer, QuadFresnel,
        PolygonFraunhofer, FresnelTransfer,
    )
}  # fmt: skip


def _check_npix(name: str, value: int, minimum: int) -> int:
    if isinstance(value, bool) or int(value) != value or value < minimum:
        raise PhysicsRangeError(f"{name} must be an integer >= {minimum}, got {value}")
    return int(value)


def _analytic_propagator(
    method: str,
    propagation: str,
    grid: ApertureGrid,
    output: AngularGrid,
    focal_length_mm: float,
    wavelengths_nm: tuple[float, ...],
    method_options: Mapping[str, Any] | None,
) -> AbstractPropagator:
    """A quad or polygon propagator: no aliasing limits, only the float type's (see
    :func:`~invglare.optics.quad.options.check_representable`)."""
    if method == "polygon" and propagation != "fraunhofer":
        raise ConfigError(
            "method = 'polygon' is a far-field (Fraunhofer) transform: polygons have no "
            "closed-form Fresnel integral; use method = 'quad' for propagation = 'fresnel'"
        )
    distance = focal_length_mm if propagation == "fresnel" else None
    check_representable(grid, output, min(wavelengths_nm), distance)
    opts = METHOD_OPTIONS[method].from_mapping(method_options)
    cls = PROPAGATOR_CLASSES[(propagation, method)]
    kwargs = {"quad" if method == "quad" else "polygon": opts}
    return cls(
        grid=grid, output=output, focal_length_mm=focal_length_mm,
        wavelengths_nm=tuple(float(w) for w in wavelengths_nm), **kwargs,
    )  # fmt: skip


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
    method_options: Mapping[str, Any] | None = None,
    wavelengths_nm: tuple[float, ...] | None = None,
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
      requested pixel scale exactly, else the MFT); ``"quad"`` (the raster's quads in
      closed form, far or near field); ``"polygon"`` (the shapes' exact transforms);
      ``"transfer"`` (Fresnel only) for the image-plane near field of
      :class:`FresnelTransfer`, whose pixels are ``pitch / focal_length_mm`` rad (a
      `pixel_scale_deg` must equal that).
    - `method_options`: the ``[model.quad]`` / ``[model.polygon]`` table
      (:class:`~invglare.optics.quad.options.QuadOptions`, `PolygonOptions`).
    - `wavelengths_nm`: every wavelength the propagator will evaluate (quad culling is
      decided for them; default the FFT wavelength and the shortest one).

    **Returns:** a :class:`FraunhoferFFT`, :class:`FraunhoferMFT`, :class:`FresnelFFT`,
    :class:`FresnelMFT`, :class:`FresnelTransfer`, :class:`QuadFraunhofer`,
    :class:`QuadFresnel` or :class:`PolygonFraunhofer` (the last three still to be
    :meth:`~AbstractPropagator.prepared` for an aperture).

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
    if method_options and method not in METHOD_OPTIONS:
        raise ConfigError(f"method = {method!r} takes no options, got {dict(method_options)}")
    if method in METHOD_OPTIONS:
        if pixel_scale_deg is None:  # the FFT's native scale, as the fast path would give
            fft_npix = max(npix, 2 * aperture_npix)
            fft_npix += fft_npix % 2
            pixel_scale_deg = math.degrees(fft_wavelength_nm * 1e-6 / (fft_npix * pitch))
        check_positive("pixel_scale_deg", pixel_scale_deg, "deg")
        waves = wavelengths_nm or (fft_wavelength_nm, shortest_wavelength_nm)
        return _analytic_propagator(
            method, propagation, ApertureGrid.from_width(aperture_npix, window_mm),
            AngularGrid(npix, pixel_scale_deg), focal_length_mm, tuple(waves), method_options,
        )  # fmt: skip
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
