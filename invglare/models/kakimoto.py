"""Glare from an obstacle image masked by a pupil: the wave-optics model of Kakimoto et al.

Light from a distant source passes an *obstacle* plane (eyelashes and lids, or a
camera's cross-screen filter) a distance ``d_o`` in front of the *pupil* (the
eye's pupil, or a camera's diaphragm) and is focused onto the retina / sensor.
In the Fraunhofer approximation the glare is the squared modulus of the Fourier
transform of the obstacle's amplitude transmission ``t_o`` masked by the pupil
function ``P`` (eq. 2-5 of the paper):

- **fixed mask** (eq. 5, ``masking="fixed"``): ``I ∝ |F[t_o(x) P(x)]|²``, the same
  PSF for every light direction;
- **position-dependent mask** (eq. 3, ``masking="position"``): the pupil projected
  back onto the obstacle plane is centred where the ray to the image point
  crosses it, so the part of the obstacle that masks the pupil depends on the
  light direction. As in the paper's implementation (sec. 4.2-4.3: the eyelash
  silhouette scrolled with the light direction), it is evaluated once per light
  direction, at the centre of that light's glare, rather than separately at
  every output pixel: the obstacle image is translated by ``-d_o * tan(angle)``
  relative to the pupil before masking, ``I ∝ |F[t_o(x + d_o tan(angle)) P(x)]|²``.
  The neglected part is the drift of the mask *within* one glare pattern: at
  an angle ``a`` from the glare centre the exact eq. 3 would move the mask by a
  further ``d_o * a``, which is small when the glare spans a few degrees and
  ``d_o`` is a few mm (it also stays below the resolution of the pattern's
  features as long as ``d_o * a`` is much smaller than the obstacle's features).

**Sign convention.** `light_angle_deg` = ``(a_x, a_y)`` is the direction of the
light in the field of view, in degrees, x to the right and y up (the axes of the
aperture grid, looking out through the aperture towards the scene). A ray from
that direction that reaches the pupil at ``x`` crossed the obstacle plane at
``x + d_o tan(a)``, so the obstacle image seen through the pupil is
``t_o(x - s)`` with ``s = -d_o tan(a)``: for a light to the right the obstacle
slides to the left over the pupil. That ``s`` is what is passed as `shift_mm` to
the aperture's ``obstacle_transmission``. (In the paper's eq. 3 the pupil is
centred at ``-(d_o / f) x_f`` on the obstacle plane; with the image point
``x_f = -f tan(a)`` this is the same statement.)

**What follows the paper and what departs.** Eq. 5 (fixed mask) and eq. 3 (the mask
scrolled with the light, evaluated per light as the paper's implementation does) are the
paper's, as are the RGB wavelengths 680 / 530 / 460 nm (``colour="paper_rgb"``) and any
picture as the obstacle or pupil (`obstacle_image`, `pupil_image` of the eye and camera
apertures, a distance `obstacle_distance_mm` in front of the pupil). Departures, each
named: PSFs are normalised to unit energy instead of the paper's ``A^2 / (lambda f)^2``
(the observation model of a fit carries the flux); ``colour="spectral"`` integrates a
spectrum instead of three lines; structures the raster cannot resolve are refused or
warned of (:mod:`invglare.models.structures`); and the eye's particles, which the paper's
eyelash model does not have (Ritschel et al. add them), scatter beyond the raster's band
in closed form (``wide_angle``). The paper's display pipeline (sigmoid, billboards) is
the render tier's: :mod:`invglare.render.composite`.

**Apertures.** Any equinox Module with these methods works (see
:class:`ObstacleAperture`), e.g. :class:`invglare.aperture.camera.CameraAperture`
and the eye aperture:

- ``pupil_transmission(grid) -> (n, n)``: ``P`` on the grid;
- ``obstacle_transmission(grid, shift_mm) -> (n, n)``: ``t_o(x - shift_mm)``, for any
  shift (it must be defined beyond the window, since lights off axis bring other
  parts of the obstacle over the pupil);
- ``extent_mm() -> float``: diameter of a disk about the axis holding the pupil;
- optionally ``with_stamp_windows(grid) -> aperture``: a copy with any static
  raster shapes fixed for `grid` (the eye's stamp windows); :meth:`KakimotoGlare.build`
  calls it so that the model works under `jit`, `vmap` and `grad`.

**Output.** Like :class:`~invglare.models.aperture_psf.AperturePSF`, PSFs are
energy per output pixel, per unit power through obstacle and pupil (per wavelength): the
raster's transmission ``sum |t_o P| pitch^2``, as in :mod:`invglare.optics.fraunhofer`
(with the FFT the sum is just under 1: the light the raster's sharp edges diffract beyond
its Nyquist angle is not held). With
``colour="paper_rgb"`` each of the R, G, B channels is a monochromatic PSF
(680, 530, 460 nm) of unit energy, as the paper's three "equal-strength, pure
coherent" lines; with ``colour="spectral"`` the spectrum is integrated through
:class:`~invglare.optics.spectral.Spectrum` (linear RGB whose Y has unit energy,
or a monochrome PSF for a single wavelength).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any, ClassVar, Protocol, Unpack, runtime_checkable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.ndimage import map_coordinates
from jaxtyping import Array, ArrayLike, Float

from invglare._core.checks import as_float, check_range, choose
from invglare._core.grids import ApertureGrid
from invglare.aperture.camera import CameraAperture, camera_to_config
from invglare.aperture.eye import EyeAperture, eye_to_config
from invglare.errors import ConfigError, PhysicsRangeError
from invglare.models.aperture_psf import output_and_spectrum_tables, propagator_table
from invglare.models.base import (
    broadcast_image,
    check_no_state,
    light_angle,
    light_angles,
    map_lights,
)
from invglare.models.raster import (
    AIRY_FIRST_ZERO,
    AbstractRasterModel,
    RasterSampling,
    build_propagator,
    raster_header,
)
from invglare.models.structures import check_structures
from invglare.optics.fraunhofer import transmitted_power
from invglare.optics.particles import particle_scatter
from invglare.optics.propagator import AbstractPropagator
from invglare.optics.spectral import (
    COPY_METHODS,
    DEFAULT_WAVELENGTHS,
    Spectrum,
    parse_wavelengths,
)

__all__ = [
    "AIRY_FIRST_ZERO",
    "COLOURS",
    "MASKINGS",
    "PAPER_RGB_NM",
    "WIDE_ANGLE",
    "KakimotoGlare",
    "ObstacleAperture",
    "kakimoto_to_config",
]

#: The two masking models: eq. 5 (fixed mask) and eq. 3 (mask moving with the light).
MASKINGS = ("fixed", "position")
#: Colour modes: the paper's three wavelengths as R, G, B, or a spectrum through `Spectrum`.
COLOURS = ("paper_rgb", "spectral")
#: The paper's wavelengths (nm) for the R, G and B channels (sec. 3.2).
PAPER_RGB_NM = (680.0, 530.0, 460.0)
#: How an eye's particles scatter beyond the raster's band: averaged over their positions,
#: with their phases, or not at all (see :meth:`KakimotoGlare.build`).
WIDE_ANGLE = ("ensemble", "phases", "none")


@runtime_checkable
class ObstacleAperture(Protocol):
    """What :class:`KakimotoGlare` needs from an aperture (eye or camera)."""

    def pupil_transmission(self, grid: ApertureGrid) -> Float[Array, "n n"]:
        """Pupil function ``P`` on `grid` (amplitude transmission in [0, 1])."""
        ...

    def obstacle_transmission(
        self, grid: ApertureGrid, shift_mm: Float[ArrayLike, " 2"]
    ) -> Float[Array, "n n"]:
        """Obstacle image translated by `shift_mm` = (x, y) mm, ``t_o(x - shift_mm)``."""
        ...

    def extent_mm(self) -> float:
        """Diameter (mm) of a disk about the axis holding the pupil (concrete)."""
        ...


class KakimotoGlare(AbstractRasterModel):
    """Glare PSF of an obstacle image masked by a pupil (Kakimoto et al., eq. 3 and 5).

    Build one with :meth:`build`, which picks the sampling (the same rules as
    :class:`~invglare.models.aperture_psf.AperturePSF`).

    **Fields:**

    - `aperture`: an :class:`ObstacleAperture` (eye or camera).
    - `propagator`: the :class:`~invglare.optics.propagator.AbstractPropagator` (aperture grid,
      output grid, FFT or MFT).
    - `spectrum`: the :class:`~invglare.optics.spectral.Spectrum`; for ``"paper_rgb"`` its
      three wavelengths are the R, G, B channels.
    - `obstacle_distance_mm`: ``d_o``, obstacle plane to pupil (mm, >= 0; array leaf).
    - `masking`: ``"fixed"`` (eq. 5) or ``"position"`` (eq. 3 as in sec. 4.2), static.
    - `colour`: ``"paper_rgb"`` or ``"spectral"``, static.
    - `max_light_angle_deg`: the largest light angle the model is meant for (static;
      see :meth:`obstacle_window_mm`).
    - `wide_angle`: ``"ensemble"``, ``"phases"`` or ``"none"`` (static): how an eye's
      particles scatter beyond the raster's band (see :meth:`build`).
    """

    aperture: Any
    propagator: AbstractPropagator
    spectrum: Spectrum
    obstacle_distance_mm: Float[Array, ""] = eqx.field(converter=as_float)
    masking: str = eqx.field(static=True, default="fixed")
    colour: str = eqx.field(static=True, default="paper_rgb")
    max_light_angle_deg: float = eqx.field(static=True, default=0.0)
    wide_angle: str = eqx.field(static=True, default="ensemble")
    centre: ClassVar[str] = "light"
    animated: ClassVar[bool] = False

    def __check_init__(self):
        if not isinstance(self.aperture, ObstacleAperture):
            raise ConfigError(
                f"the Kakimoto model needs an aperture with pupil_transmission(grid), "
                f"obstacle_transmission(grid, shift_mm) and extent_mm() (an eye or camera "
                f"aperture), got {type(self.aperture).__name__}"
            )
        choose("masking", self.masking, MASKINGS)
        choose("colour", self.colour, COLOURS)
        choose("wide_angle", self.wide_angle, WIDE_ANGLE)
        check_range("obstacle_distance_mm", self.obstacle_distance_mm, 0.0, unit="mm")
        if self.colour == "paper_rgb" and self.spectrum.wavelengths_nm.shape[0] != 3:
            raise ConfigError(
                "colour = 'paper_rgb' needs exactly three wavelengths (R, G, B), got "
                f"{self.spectrum.wavelengths_nm.shape[0]}"
            )

    # ----------------------------------------------------------------------------- build

    @classmethod
    def build(
        cls,
        aperture: ObstacleAperture,
        *,
        focal_length_mm: float,
        obstacle_distance_mm: float,
        colour: str = "paper_rgb",
        masking: str = "fixed",
        wavelengths_nm: Any = None,
        max_light_angle_deg: float = 0.0,
        method: str = "auto",
        spectral: str = "exact",
        reference_wavelength_nm: float = 575.0,
        illuminant: str = "E",
        colourspace: str = "sRGB",
        wide_angle: str = "ensemble",
        **raster: Unpack[RasterSampling],
    ) -> KakimotoGlare:
        """Choose the sampling for an aperture and validate every choice.

        **Arguments:**

        - `aperture`: eye or camera aperture (see :class:`ObstacleAperture`).
        - `focal_length_mm`: pupil-to-retina / lens-to-sensor distance ``f`` (mm).
        - `obstacle_distance_mm`: ``d_o`` (mm, >= 0), e.g. ~8 mm from lashes to the
          pupil of an eye, or the distance of a filter in front of a camera's stop.
        - `npix`, `pixel_scale_deg`: the output grid (default 512 pixels); without a pixel
          scale the FFT's native scale at the shortest computed wavelength is used.
        - `aperture_npix`, `window_mm`: the aperture raster (default 256 pixels); the window
          defaults to the pupil's extent plus two pixels on each side.
        - `colour`: ``"paper_rgb"`` (R, G, B = monochromatic PSFs at `wavelengths_nm`,
          default 680 / 530 / 460 nm, in that order) or ``"spectral"`` (`wavelengths_nm`
          integrated to linear RGB by `Spectrum`, default ``"380:770:32"``; a single
          wavelength gives a monochrome PSF).
        - `masking`: ``"fixed"`` (eq. 5) or ``"position"`` (eq. 3, sec. 4.2).
        - `max_light_angle_deg`: largest light angle (deg) the model will see; it sets
          :meth:`obstacle_window_mm`. The propagation window is *not* enlarged for it:
          the grid is the pupil plane and the obstacle is translated across it, so
          ``t_o P`` stays inside the pupil for any shift and the intensity does not
          depend on where the field sits in the window. Enlarging the window would only
          coarsen the raster.
        - `propagation`, `method`, `method_options`, `spectral`, `reference_wavelength_nm`,
          `illuminant`, `colourspace`: as for
          :meth:`~invglare.models.aperture_psf.AperturePSF.build` (`spectral` applies to
          ``colour="spectral"``). The obstacle image is a raster: ``method = "polygon"``
          is refused, and ``"quad"`` needs ``masking = "fixed"`` (its quadtree is decided
          on one raster; a position-dependent mask is another raster per light).
        - `wide_angle`: an eye's particles (cornea cells, lens and vitreous particles)
          diffract far beyond the raster's alias-free band ``lambda / (2 pitch)``. With
          ``"ensemble"`` (default) or ``"phases"`` an eye with particles may have a
          Fraunhofer MFT output wider than that band: the raster gives the PSF inside it
          and the particles' closed-form scatter
          (:func:`~invglare.optics.particles.particle_scatter`: Babinet's disks, averaged
          over positions or with their phases) the rest, so the veil reaches the angles
          the CIE function describes; the pupil's and lashes' own diffraction beyond the
          band is not represented. ``"none"`` refuses such an output, as for any model.

        **Raises:** `PhysicsRangeError` for a pupil larger than `window_mm`, a negative
        obstacle distance, or a sampling that would alias; `ConfigError` for an
        unknown `colour` / `masking` / `method` or an aperture without the three methods.

        **Example:**

        ```python
        camera = CameraAperture(Diaphragm(6, 8.0, 50.0),
                                filter=CrossScreen((0.0, 90.0), 0.2, 0.1))
        model = KakimotoGlare.build(camera, focal_length_mm=50.0,
                                    obstacle_distance_mm=20.0, npix=256)
        rgb = model()                       # (256, 256, 3)
        psfs = model.batch(jnp.array([[0.0, 0.0], [5.0, 0.0]]))
        ```
        """
        choose("colour", colour, COLOURS)
        choose("masking", masking, MASKINGS)
        if method == "polygon":
            raise ConfigError(
                "method = 'polygon' transforms shapes, and the Kakimoto model's field is a "
                "raster (an obstacle image times a pupil); use method = 'quad', 'fft' or 'mft'"
            )
        if method == "quad" and masking == "position":
            raise ConfigError(
                "method = 'quad' decides its quadtree on one raster, and masking = "
                "'position' makes another raster for every light; use masking = 'fixed' "
                "or method = 'fft' / 'mft'"
            )
        choose("wide_angle", wide_angle, WIDE_ANGLE)
        check_range("obstacle_distance_mm", obstacle_distance_mm, 0.0, unit="mm")
        check_range("max_light_angle_deg", max_light_angle_deg, 0.0, unit="deg")
        if not max_light_angle_deg < 90.0:
            raise PhysicsRangeError(
                f"max_light_angle_deg must be < 90 deg, got {max_light_angle_deg!r}"
            )
        if not isinstance(aperture, ObstacleAperture):
            raise ConfigError(
                "the Kakimoto model needs an aperture with pupil_transmission(grid), "
                "obstacle_transmission(grid, shift_mm) and extent_mm(), got "
                f"{type(aperture).__name__}"
            )
        if colour == "paper_rgb":
            wl = parse_wavelengths(PAPER_RGB_NM if wavelengths_nm is None else wavelengths_nm)
            if wl.shape != (3,):
                raise ConfigError(
                    f"colour = 'paper_rgb' takes three wavelengths (R, G, B), got {wl.tolist()}"
                )
            spectrum = Spectrum.build(wl, illuminant=illuminant, colourspace=colourspace)
            # Three exact transforms on one output grid: the sampling is chosen at the
            # shortest wavelength, so the FFT-native pixel scale (when none is given) stays
            # alias-free for all three.
            sampling = Spectrum.build(np.sort(wl), illuminant=illuminant, colourspace=colourspace)
        else:
            wl = parse_wavelengths(
                DEFAULT_WAVELENGTHS if wavelengths_nm is None else wavelengths_nm
            )
            kwargs = dict(
                spectral=spectral,
                reference_wavelength_nm=reference_wavelength_nm,
                illuminant=illuminant,
                colourspace=colourspace,
            )
            spectrum = Spectrum.build(wl, **kwargs)
            copies = spectral in COPY_METHODS
            sampling = spectrum if copies else Spectrum.build(np.sort(wl), **kwargs)
        propagator = build_propagator(
            float(aperture.extent_mm()),
            sampling,
            focal_length_mm=focal_length_mm,
            method=method,
            beyond_band=wide_angle != "none" and bool(getattr(aperture, "particles", ())),
            **raster,
        )
        # Structures finer than the raster: gratings it aliases are refused, the rest warned.
        check_structures(
            aperture,
            propagator.grid,
            tuple(float(w) for w in np.asarray(spectrum.wavelengths_nm).reshape(-1)),
            None
            if propagator.method == "transfer"
            else math.radians(float(propagator.output.half_field_deg)),
        )
        # Apertures whose rasters have data-dependent static shapes (the eye's local stamps)
        # fix them for this grid here, so that the model can be jitted and differentiated.
        fix_windows = getattr(aperture, "with_stamp_windows", None)
        if callable(fix_windows):
            aperture = fix_windows(propagator.grid)
        model = cls(
            aperture=aperture,
            propagator=propagator,
            spectrum=spectrum,
            obstacle_distance_mm=obstacle_distance_mm,
            masking=masking,
            colour=colour,
            max_light_angle_deg=float(max_light_angle_deg),
            wide_angle=wide_angle,
        )
        prepared = propagator.prepared(model.field())
        return model if prepared is propagator else dataclasses.replace(model, propagator=prepared)

    # ----------------------------------------------------------------------------- fields

    def obstacle_shift_mm(self, light_angle_deg: Float[ArrayLike, " 2"]) -> Float[Array, " 2"]:
        """Translation (mm) of the obstacle image over the pupil, ``-d_o tan(angle)``."""
        angle = as_float(light_angle_deg)
        return -self.obstacle_distance_mm * jnp.tan(jnp.deg2rad(angle))

    def _shift(self, light_angle_deg, dtype) -> Float[Array, " 2"]:
        if self.masking == "fixed":
            return jnp.zeros(2, dtype=dtype)
        return self.obstacle_shift_mm(light_angle_deg).astype(dtype)

    def field(self, light_angle_deg: Float[ArrayLike, " 2"] = (0.0, 0.0)) -> Float[Array, "n n"]:
        """The masked obstacle ``t_o P`` on the propagator's grid, for a light at that angle.

        With ``masking="fixed"`` the angle is ignored (eq. 5).
        """
        grid = self.propagator.grid
        pupil = self.aperture.pupil_transmission(grid)
        shift = self._shift(light_angle_deg, pupil.dtype)
        return self.aperture.obstacle_transmission(grid, shift) * pupil

    @property
    def scatters_beyond_band(self) -> bool:
        """Whether the output reaches beyond the raster's band with an eye's particles there."""
        core = getattr(self.propagator, "core_npix", None)
        return (
            self.wide_angle != "none"
            and isinstance(self.aperture, EyeAperture)
            and bool(self.aperture.particles)
            and core is not None
            and core < self.propagator.output.npix
        )

    def _scatterers(self, light_angle_deg) -> tuple[Array, Array, Array]:
        """Radii, amplitudes ``w t`` and centres of every particle, for the wide-angle term.

        ``t`` is the light reaching a particle: the open pupil times the (shifted)
        obstacle, bilinear at its centre.
        """
        eye, grid = self.aperture, self.propagator.grid
        lit = eye.opening(grid)
        lit = lit * eye.obstacle_transmission(grid, self._shift(light_angle_deg, lit.dtype))
        centre = grid.npix // 2
        radii, amps, centres = [], [], []
        for population in eye.particles:
            xy = population.centers_mm()
            rows = xy[:, 1] / grid.pitch_mm + centre
            cols = xy[:, 0] / grid.pitch_mm + centre
            t = map_coordinates(lit, [rows, cols], order=1, mode="constant", cval=0.0)
            radii.append(population.radii_mm())
            amps.append(population.weights() * t)
            centres.append(xy)
        return jnp.concatenate(radii), jnp.concatenate(amps), jnp.concatenate(centres)

    def _psf(
        self, field: Float[Array, "n n"], light_angle_deg=(0.0, 0.0)
    ) -> Float[Array, "npix npix"] | Float[Array, "npix npix 3"]:
        if self.scatters_beyond_band:
            prop = self.propagator
            radii, amps, centres = self._scatterers(light_angle_deg)
            power = transmitted_power(field, prop.grid.pitch_mm)
            beyond = jnp.asarray(_beyond_core(prop.output.npix, prop.core_npix), field.dtype)

            def monochrome(wavelength_nm):
                veil = particle_scatter(
                    radii, amps, centres, prop.output, wavelength_nm, power, self.wide_angle
                )
                return prop(field, wavelength_nm) + beyond * veil

        else:

            def monochrome(wavelength_nm):
                return self.propagator(field, wavelength_nm)

        if self.colour == "paper_rgb":
            # R, G, B in the order of the spectrum's wavelengths; channels last.
            return jnp.moveaxis(jax.vmap(monochrome)(self.spectrum.wavelengths_nm), 0, -1)
        return self.spectrum.integrate(monochrome)

    # ----------------------------------------------------------------------------- outputs

    def __call__(
        self, light_angle_deg: Float[ArrayLike, " 2"] | None = None, *, state: Any = None
    ) -> Float[Array, "npix npix"] | Float[Array, "npix npix 3"]:
        """Glare PSF for a light at `light_angle_deg` = (x, y) deg (None: on axis).

        **Returns:** ``(npix, npix, 3)`` for RGB, ``(npix, npix)`` for a single
        wavelength. The PSF is centred at ``(npix // 2, npix // 2)`` whatever the angle:
        place it at the light's image position when compositing.

        **Example:**

        ```python
        psf = model((3.0, -1.0))   # light 3 deg right and 1 deg down
        ```
        """
        angle = light_angle(light_angle_deg)
        check_no_state(self, state)
        return self._psf(self.field(angle), angle)

    def batch(
        self, light_angles_deg: Float[ArrayLike, "K 2"], batch_size: int | None = None
    ) -> Float[Array, "K npix npix"] | Float[Array, "K npix npix 3"]:
        """Glare PSFs for many light directions in one call (``vmap`` over the angles).

        **Arguments:**

        - `light_angles_deg`: ``(K, 2)`` angles (deg), as for :meth:`__call__`.
        - `batch_size`: if given, the angles are processed `batch_size` at a time
          (``lax.map``), bounding memory at ``batch_size`` fields and PSFs.

        With ``masking="fixed"`` every PSF is the same, computed once and broadcast.

        **Example:**

        ```python
        angles = jnp.stack([jnp.linspace(-10, 10, 64), jnp.zeros(64)], axis=-1)
        psfs = eqx.filter_jit(model.batch)(angles)   # (64, npix, npix, 3)
        ```
        """
        angles = light_angles(light_angles_deg)
        if self.masking == "fixed":
            return broadcast_image(self._psf(self.field()), angles.shape[0])
        return map_lights(lambda angle: self._psf(self.field(angle), angle), angles, batch_size)

    # ------------------------------------------------------------------ the model interface

    @property
    def shift_invariant(self) -> bool:
        """Eq. 5 (fixed mask) is shift invariant; eq. 3 (the mask moves) is not."""
        return self.masking == "fixed"

    def spot_raster(self) -> Float[Array, "n n"]:
        return self.aperture.pupil_transmission(self.propagator.grid)

    def header(self) -> dict[str, Any]:
        return raster_header(self)

    def sized_for(self, others: Sequence[KakimotoGlare]) -> KakimotoGlare:
        """The eye's stamp windows sized for this model and `others` (no headroom).

        Comes back unchanged for an aperture without stamp windows (a camera) and where
        the others' aperture grids differ from this one's (a free grid pitch sets a
        window's size in pixels).
        """
        grid = self.propagator.grid
        if not isinstance(self.aperture, EyeAperture):
            return self
        if any(not _same_grid(o.propagator.grid, grid) for o in others):
            return self
        fitted = self.aperture.with_stamp_windows(
            grid, headroom=1.0, also=[o.aperture for o in others]
        )
        return eqx.tree_at(lambda m: m.aperture, self, fitted)

    def to_config(self) -> dict[str, Any]:
        choices = kakimoto_to_config(self)
        table = {"kind": _aperture_kind(self.aperture), **propagator_table(self.propagator)}
        table |= {k: choices[k] for k in _GLARE_KEYS}
        table[table["kind"]] = _aperture_table(self.aperture)
        return {"model": table, **output_and_spectrum_tables(self.propagator, self.spectrum)}

    # ----------------------------------------------------------------------------- helpers

    def transmitted_fraction(
        self, light_angle_deg: Float[ArrayLike, " 2"] = (0.0, 0.0)
    ) -> Float[Array, ""]:
        """Fraction of the power through the pupil that also passes the obstacle.

        ``sum |t_o P| / sum |P|`` (open areas, the PSFs' normalisation) for a light at
        `light_angle_deg`. The PSFs are per unit power through the aperture, so a
        renderer that wants a light partly hidden behind lashes to look dimmer
        multiplies by this.
        """
        pupil = self.aperture.pupil_transmission(self.propagator.grid)
        field = self.field(light_angle_deg)
        return jnp.sum(jnp.abs(field)) / jnp.maximum(jnp.sum(jnp.abs(pupil)), 1e-30)

    def obstacle_window_mm(self) -> Float[Array, ""]:
        """Width (mm) of the obstacle plane seen by lights up to `max_light_angle_deg`.

        ``window + 2 d_o tan(max angle)``: an obstacle defined by a finite image (the
        paper's eyelash silhouette, "wider than it is shown") must cover this square
        for ``masking="position"`` to see obstacle everywhere it looks.
        """
        shift = self.obstacle_distance_mm * math.tan(math.radians(self.max_light_angle_deg))
        return self.propagator.grid.width_mm + 2.0 * shift


#: The [model] keys of the Kakimoto choices (beside the propagator's).
_GLARE_KEYS = ("obstacle_distance_mm", "masking", "colour", "max_light_angle_deg", "wide_angle")


def _beyond_core(npix: int, core_npix: int) -> np.ndarray:
    """1 outside the central ``core_npix`` square of an ``npix`` grid, 0 inside."""
    inside = np.zeros((npix, npix))
    lo = npix // 2 - core_npix // 2
    inside[lo : lo + core_npix, lo : lo + core_npix] = 1.0
    return 1.0 - inside


def _same_grid(a: ApertureGrid, b: ApertureGrid) -> bool:
    return a.npix == b.npix and float(a.pitch_mm) == float(b.pitch_mm)


def _aperture_kind(aperture: Any) -> str:
    if isinstance(aperture, EyeAperture):
        return "eye"
    if isinstance(aperture, CameraAperture):
        return "camera"
    raise ConfigError(f"no config form for a Kakimoto model of a {type(aperture).__name__}")


def _aperture_table(aperture: Any) -> dict[str, Any]:
    if isinstance(aperture, EyeAperture):
        return eye_to_config(aperture)
    return camera_to_config(aperture)


def kakimoto_to_config(model: KakimotoGlare) -> dict[str, Any]:
    """The model-level choices of a Kakimoto model, as plain values.

    The keys are the keyword arguments of :meth:`KakimotoGlare.build`, so
    ``KakimotoGlare.build(aperture, **kakimoto_to_config(model))`` rebuilds the same
    model (the aperture is written by its own builder, e.g.
    :func:`invglare.aperture.camera.camera_to_config`). The output pixel scale and
    window are written explicitly, even when they were defaults.

    **Example:**

    ```python
    cfg = kakimoto_to_config(model)   # {"masking": "fixed", "colour": "paper_rgb", ...}
    ```
    """
    prop = model.propagator
    spec = model.spectrum
    return {
        "focal_length_mm": float(prop.focal_length_mm),
        "obstacle_distance_mm": float(model.obstacle_distance_mm),
        "masking": model.masking,
        "colour": model.colour,
        "wavelengths_nm": [float(w) for w in np.asarray(spec.wavelengths_nm, dtype=float)],
        "max_light_angle_deg": float(model.max_light_angle_deg),
        "wide_angle": model.wide_angle,
        "npix": int(prop.output.npix),
        "pixel_scale_deg": float(prop.output.pixel_scale_deg),
        "aperture_npix": int(prop.grid.npix),
        "window_mm": float(prop.grid.width_mm),
        "propagation": prop.propagation,
        "method": prop.method,
        "spectral": spec.spectral,
        "reference_wavelength_nm": float(spec.reference_wavelength_nm),
        "illuminant": spec.illuminant,
        "colourspace": spec.colourspace,
    }
