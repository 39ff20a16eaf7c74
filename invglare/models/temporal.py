"""Temporal glare: the dynamic human eye of Ritschel et al. (2009), frame by frame.

Every frame (sec. 5 of the paper):

1. the dynamics (:mod:`invglare.dynamics`) give the frame's pupil diameter (eq. 1-2),
   lid opening (blinks, squint), lens deformation and vitreous rotation;
2. they are applied to an :class:`~invglare.aperture.eye.EyeAperture` with
   ``eqx.tree_at``: pupil diameter, lid openings, and per-particle offsets
   (`Particles.offsets_mm`) moving lens-nucleus particles through the lens mesh and
   vitreous particles with the rigid body; cornea cells and gratings stay put;
3. the aperture is propagated with the Fresnel term ``E`` at 575 nm (eq. 3; see "The
   Fresnel term E" below): the monochromatic PSF ``F_575``;
4. the spectral PSF is the sum of `n` scaled copies of ``F_575`` (n = 32 over
   380-770 nm), weighted in XYZ and turned into linear RGB;
5. it is convolved with the HDR frame (FFT convolution) and tone-mapped (gamma 2.2 as
   in the paper, or any operator of :mod:`invglare.render.tonemap`): that step is the
   render tier's, :mod:`invglare.render.temporal_frames` (`render_frame`,
   `render_sequence`); the model carries the tone map's name and parameters as plain
   configuration for it.

A sequence is one `lax.scan` over the dynamics state, so an animation is one compiled
call. The parts of the aperture that do not move (cornea cells, gratings, the Fresnel
term, and the lids with their lashes while no blink is under way) are rasterised once
per sequence and reused by every frame; a blink re-rasterises the lids of its frames
only (`lax.cond`).

**The Fresnel term E** (eq. 3, ``fresnel``). The paper multiplies the aperture by
``E = exp(i pi r^2 / (lambda d))`` with ``d`` the pupil-to-retina distance and takes one
FFT. Three named choices:

- ``"retina"`` (default, the paper's equation as printed): ``E`` at the pupil-to-retina
  distance `focal_length_mm` (17 mm by default; 17-24 mm in real eyes). There the raster
  cannot resolve ``E`` (its phase oscillates at hundreds of cycles per mm at the pupil's
  edge), so eq. 3 is evaluated in its equivalent convolution form, the aperture convolved
  with the Fresnel kernel (:class:`~invglare.optics.propagator.FresnelTransfer`), which is
  alias-free at these distances for any raster: the PSF lies on the retina at the
  aperture pitch (pixels of ``pitch / d`` rad) and does not depend on the raster's size
  beyond its sampling. Eq. 3 has no lens in it, so at 17 mm it is the pupil's Fresnel
  shadow (Fresnel number ``r^2 / (lambda d)`` of several hundred): a disk ``p / d`` rad
  across (20 deg for a 6 mm pupil), fringed at its edge, with the particles' and lashes'
  diffraction on it. That is what the paper's formula says; a real eye focuses the light
  (the Fraunhofer pattern of the other models), which the next two choices give.
- ``"effective"``: ``E`` at an explicit `fresnel_distance_mm`, by one FFT at the native
  scale. An approximation, named as one: through an eye focused at infinity it is a
  defocus of ``1000 / d`` dioptres (600 mm: 1.67 D), which gives the pattern a Fresnel
  character at a distance the raster resolves (the model refuses a raster that aliases
  ``E`` and says how many samples it needs). The distance is yours, never derived from
  the raster.
- ``"none"``: ``E = 1``, the Fraunhofer pattern of an eye in focus (Kakimoto et al.).

**Brightness** (``brightness``). ``"transmitted"`` (default, the paper's eq. 3): the PSF
carries ``K = 1 / (lambda d)^2`` of eq. 3, whose retinal image holds the power the
aperture transmits (mm^2 for a unit irradiance: its open area, ``sum |t| pitch^2``):
the glare grows with the pupil's area, dims as the pupil constricts and goes dark in a
blink; set the tone map's exposure for it. ``"unit"``: unit energy per wavelength, as
every static model (a departure, for comparing shapes).

**Field.** The PSF covers the raster's band (the FFT's field, or the image-plane window
of ``"retina"``): the particles' diffraction beyond it, several degrees for cornea cells,
is not added here (a :class:`~invglare.errors.RasterWarning` names the raster that would
carry it); the eye kind adds it in closed form (``wide_angle``,
:mod:`invglare.optics.particles`).

**Spectrum.** The scaled copies (``spectral = "scaled"``) each keep the reference PSF's
energy (``copy_weighting = "energy"``, the default: what per-wavelength PSFs of a fixed
aperture do). The paper's printed sum is a plain look-up ``F_575(x 575 / lambda)``, whose
copy at ``lambda`` carries ``(lambda / 575)^2`` of it (1.79 at 770 nm, 0.44 at 380 nm
relative to the default): ``copy_weighting = "paper"`` gives it
(:func:`invglare.optics.spectral.copy_weights`). The copies' magnification itself is exact
only for Fraunhofer PSFs (the paper's approximation, kept in every mode).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Key

from invglare._core.checks import as_float, as_key, is_concrete
from invglare._core.maths import safe_sqrt
from invglare.aperture.eye import EyeAperture, Particles, eye_to_config
from invglare.dynamics import (
    DynamicsState,
    EyeDynamics,
    FrameValues,
    hippus_scale,
    max_hippus_amplitude_mm,
)
from invglare.dynamics.noise import uniform
from invglare.dynamics.pupil import MOON_SPENCER_RANGE_MM
from invglare.errors import ConfigError, InputDataError, PhysicsRangeError
from invglare.models.base import AbstractShiftInvariantModel, light_angle
from invglare.models.raster import (
    AbstractRasterModel,
    build_propagator,
    default_window_mm,
    raster_header,
)
from invglare.models.structures import check_structures
from invglare.optics.fraunhofer import intensity_fft, open_area_px
from invglare.optics.fresnel import fresnel_chirp_aliased, fresnel_phase
from invglare.optics.propagator import AbstractPropagator
from invglare.optics.spectral import (
    DEFAULT_WAVELENGTHS,
    Spectrum,
    copy_weights,
    scaled_copies,
    xyz_to_rgb,
)

__all__ = [
    "BRIGHTNESS",
    "FRESNEL_MODES",
    "SequenceConstants",
    "TemporalGlare",
    "check_n_frames",
    "frame_luminance_cd_m2",
    "head_motion",
]

#: How a frame's PSF is scaled: by the power the aperture transmits (mm^2; the paper's K of
#: eq. 3, the default), or to unit energy.
BRIGHTNESS = ("transmitted", "unit")
#: Where eq. 3's Fresnel term E is taken: at the pupil-to-retina distance, at an explicit
#: effective distance (an approximation), or not at all (E = 1).
FRESNEL_MODES = ("retina", "effective", "none")
#: A real eye's pupil-to-retina distance (mm), the default of eq. 3's d.
EYE_FOCAL_LENGTH_MM = 17.0
#: The pupil-to-retina distances (mm) ``fresnel = "retina"`` accepts: eyes from a small
#: child's to a long myope's, with room on each side.
EYE_DISTANCE_RANGE_MM = (10.0, 40.0)
#: Regions whose particles the dynamics move.
_MOVING = ("lens_nucleus", "vitreous")
# fold_in tag of the particle depths (their coordinate along the optical axis).
_DEPTH_TAG = 4242
_REC709_Y = (0.2126, 0.7152, 0.0722)


def frame_luminance_cd_m2(
    image: Float[ArrayLike, "H W *c"], luminance_scale: float | Float[ArrayLike, ""] = 1.0
) -> Float[Array, ""]:
    """Mean luminance (cd/m^2) of a frame: Rec. 709 Y of RGB (or the mono values) times scale."""
    image = as_float(image)
    y = image if image.ndim == 2 else image @ jnp.asarray(_REC709_Y, image.dtype)
    return jnp.mean(y) * luminance_scale


class SequenceConstants(eqx.Module):
    """The per-sequence constants of the pipeline (:meth:`TemporalGlare.sequence_constants`,
    computed inside the traced call and reused by every frame)."""

    fresnel: Array  # E at the reference wavelength ("effective"; 1 otherwise)
    log_static: Array  # log-transmission of the particles and gratings that do not move
    obstacle: Array  # lids and lashes at the resting open fraction
    open_fraction: Array  # that resting open fraction (1 - squint)
    depths_mm: tuple  # per moving population: the particles' coordinate along the axis


class TemporalGlare(AbstractRasterModel, AbstractShiftInvariantModel):
    """The temporal glare model: a dynamic eye, its spectral Fresnel PSF, glare on frames.

    Build one with :meth:`build` (or from a config with
    :func:`invglare.config.temporal.temporal_from_config`).

    **Fields:**

    - `eye`: the eye at rest (:class:`~invglare.aperture.eye.EyeAperture`, stamp windows
      fixed for the grid); parameters addressed by path, e.g. ``"eye.pupil.diameter_mm"``.
    - `dynamics`: the :class:`~invglare.dynamics.EyeDynamics` parameters.
    - `key`: randomness of the dynamics and of the particles' depths.
    - `propagator`: aperture grid and FFT output grid (Fresnel, reference wavelength).
    - `spectrum`: wavelengths and weights (scaled copies of the reference PSF).
    - `field_luminance_cd_m2`: luminance the eye is adapted to when no frame says
      otherwise (for :meth:`__call__` and :meth:`psf_sequence` without a state).
    - `luminance_scale`: cd/m^2 per unit of a frame's pixel values.
    - `fps`: frames per second (static).
    - `psf_scale_deg`: static copy of the PSF's pixel scale (deg), set by :meth:`build`
      (resampling to a frame's scale needs it concrete under `jit`).
    - `lids_move`: static, set by :meth:`build` from whether the dynamics blink: when
      False the lids and lashes are rasterised once per sequence and never per frame.
    - `brightness`: ``"transmitted"`` or ``"unit"`` (static; see the module docstring).
    - `fresnel`: ``"retina"``, ``"effective"`` or ``"none"`` (static; the module
      docstring); `fresnel_distance_mm`: the effective distance of ``"effective"``.
    - `tonemap_name`, `tonemap_params`: the display operator and its parameters (static,
      plain data: :mod:`invglare.render.temporal_frames` checks and applies them).

    Frames (convolution with an HDR image, tone mapping) are rendered by
    :func:`invglare.render.temporal_frames.render_frame` and
    :func:`~invglare.render.temporal_frames.render_sequence`, which take the model.
    """

    eye: EyeAperture
    dynamics: EyeDynamics
    key: Key[Array, ""] = eqx.field(converter=as_key)
    propagator: AbstractPropagator
    spectrum: Spectrum
    field_luminance_cd_m2: Float[Array, ""] = eqx.field(converter=as_float)
    luminance_scale: Float[Array, ""] = eqx.field(converter=as_float)
    fps: float = eqx.field(static=True)
    lids_move: bool = eqx.field(static=True, default=True)
    psf_scale_deg: float = eqx.field(static=True, default=0.0)
    brightness: str = eqx.field(static=True, default="transmitted")
    fresnel: str = eqx.field(static=True, default="retina")
    fresnel_distance_mm: float | None = eqx.field(static=True, default=None)
    tonemap_name: str = eqx.field(static=True, default="gamma")
    tonemap_params: tuple[tuple[str, float], ...] = eqx.field(
        static=True, default=(("exposure", 1.0), ("gamma", 2.2))
    )
    centre: ClassVar[str] = "light"
    animated: ClassVar[bool] = True

    # ----------------------------------------------------------------------------- build

    @classmethod
    def build(
        cls,
        eye: EyeAperture,
        dynamics: EyeDynamics | None = None,
        *,
        focal_length_mm: float = EYE_FOCAL_LENGTH_MM,
        fresnel: str = "retina",
        fresnel_distance_mm: float | None = None,
        npix: int = 512,
        aperture_npix: int | None = None,
        window_mm: float | None = None,
        wavelengths_nm: Any = DEFAULT_WAVELENGTHS,
        reference_wavelength_nm: float = 575.0,
        illuminant: str = "E",
        colourspace: str = "sRGB",
        fps: float = 30.0,
        key: Key[Array, ""] | int = 0,
        field_luminance_cd_m2: float = 100.0,
        luminance_scale: float = 1.0,
        brightness: str = "transmitted",
        copy_weighting: str = "energy",
        tonemap_name: str = "gamma",
        tonemap_params: dict[str, float] | None = None,
    ) -> TemporalGlare:
        """Choose the sampling for an eye and its dynamics, validating every choice.

        **Arguments:**

        - `eye`: the eye at rest; its pupil diameter is the mean diameter when
          ``dynamics.pupil.from_luminance`` is False.
        - `dynamics`: :class:`~invglare.dynamics.EyeDynamics` (default: the paper's).
        - `focal_length_mm`: pupil-to-retina distance ``d`` (mm; 17 by default), eq. 3's
          distance with ``fresnel="retina"``.
        - `fresnel`: ``"retina"`` (E at `focal_length_mm`, alias-free by the Fresnel
          kernel), ``"effective"`` (E at `fresnel_distance_mm`, an approximation: a defocus
          of ``1000 / d`` D) or ``"none"`` (E = 1); see the module docstring.
        - `fresnel_distance_mm`: the effective distance (mm), required by ``"effective"``
          and refused otherwise.
        - `npix`: output PSF size (FFT size, px).
        - `aperture_npix`: aperture raster size (default ``npix // 2``, the FFT pads 2x).
        - `window_mm`: aperture window (default: the largest pupil the dynamics reach
          plus two pixels each side).
        - `wavelengths_nm`: spectral samples (default 380:770:32, the paper's); one
          wavelength gives a monochrome PSF.
        - `reference_wavelength_nm`: the wavelength of the one FFT (575 nm).
        - `illuminant`, `colourspace`: the light's spectrum and the RGB space.
        - `fps`: frame rate (1/s).
        - `key`: key (or int seed) of the dynamics.
        - `field_luminance_cd_m2`: default adaptation luminance (cd/m^2).
        - `luminance_scale`: cd/m^2 per frame pixel unit.
        - `brightness`: ``"transmitted"`` (eq. 3's K: the PSF holds the transmitted power,
          mm^2) or ``"unit"``.
        - `copy_weighting`: ``"energy"`` or ``"paper"`` (the module docstring).
        - `tonemap_name`, `tonemap_params`: a tone map of :data:`invglare.render.TONEMAPS`
          and its keyword parameters (default gamma 2.2, exposure 1), kept as plain data;
          the render tier checks them against its registry when it displays a frame
          (:mod:`invglare.render.temporal_frames`).

        **Raises:** `ConfigError` for unknown choices or an unstable frame rate,
        `PhysicsRangeError` for values out of range or a Fresnel term the raster aliases.

        **Example:**

        ```python
        model = TemporalGlare.build(night_eye(0), npix=256)
        state, psfs = jax.jit(lambda m: m.psf_sequence(8, 1.0))(model)  # (8, 256, 256, 3)
        ```
        """
        dynamics = EyeDynamics() if dynamics is None else dynamics
        if not isinstance(eye, EyeAperture):
            raise ConfigError(f"the temporal model needs an EyeAperture, got {type(eye).__name__}")
        if not isinstance(dynamics, EyeDynamics):
            raise ConfigError(f"dynamics must be an EyeDynamics, got {type(dynamics).__name__}")
        if brightness not in BRIGHTNESS:
            raise ConfigError(f"brightness = {brightness!r} is not one of {', '.join(BRIGHTNESS)}")
        if fresnel not in FRESNEL_MODES:
            raise ConfigError(f"fresnel = {fresnel!r} is not one of {', '.join(FRESNEL_MODES)}")
        if (fresnel == "effective") != (fresnel_distance_mm is not None):
            raise ConfigError(
                "fresnel = 'effective' needs fresnel_distance_mm (the effective distance of E, "
                "mm), and only it takes one"
                if fresnel == "effective"
                else f"fresnel_distance_mm is the distance of fresnel = 'effective', not of "
                f"fresnel = {fresnel!r}; drop it or set fresnel = 'effective'"
            )
        for name, value in (
            ("focal_length_mm", focal_length_mm),
            ("fresnel_distance_mm", fresnel_distance_mm),
        ):
            if value is not None and not (
                isinstance(value, int | float) and math.isfinite(value) and value > 0
            ):
                raise PhysicsRangeError(f"{name} must be a finite number > 0 mm, got {value!r}")
        lo_d, hi_d = EYE_DISTANCE_RANGE_MM
        if fresnel == "retina" and not lo_d <= focal_length_mm <= hi_d:
            raise PhysicsRangeError(
                f"focal_length_mm = {focal_length_mm:g} is eq. 3's pupil-to-retina distance, "
                f"{lo_d:g}-{hi_d:g} mm in an eye; for E at an effective distance (an "
                f"approximation) set fresnel = 'effective' and fresnel_distance_mm = "
                f"{focal_length_mm:g}"
            )
        if not (isinstance(fps, int | float) and math.isfinite(fps) and fps > 0):
            raise PhysicsRangeError(f"fps must be a finite number > 0 frames/s, got {fps!r}")
        if tonemap_params is None:
            params = {"exposure": 1.0, "gamma": 2.2} if tonemap_name == "gamma" else {}
        else:
            params = dict(tonemap_params)
        # The tone map is the render tier's (it is checked against its registry there, by
        # invglare.render.temporal_frames, when a frame is displayed); here only its form.
        if not isinstance(tonemap_name, str) or not tonemap_name:
            raise ConfigError(f"tonemap_name must be a tone map's name, got {tonemap_name!r}")
        for name, value in params.items():
            if not (
                isinstance(name, str)
                and isinstance(value, int | float)
                and not isinstance(value, bool)
                and math.isfinite(value)
            ):
                raise ConfigError(
                    f"tonemap_params must map names to finite numbers, got {name!r} = {value!r}"
                )
        for name, value in (
            ("field_luminance_cd_m2", field_luminance_cd_m2),
            ("luminance_scale", luminance_scale),
        ):
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise PhysicsRangeError(f"{name} must be a finite number >= 0, got {value!r}")
        dynamics.check_time_step(1.0 / float(fps))
        pupil = dynamics.pupil
        p_max = float(pupil.max_diameter_mm)
        amplitude = float(pupil.hippus_amplitude_mm)
        if pupil.from_luminance:
            lo, hi = MOON_SPENCER_RANGE_MM
        else:
            lo = hi = float(eye.pupil.diameter_mm)
            if not lo < p_max:
                raise PhysicsRangeError(
                    f"eye pupil diameter_mm = {lo:g} mm must be below the dynamics' "
                    f"max_diameter_mm = {p_max:g} mm"
                )
            bound = max_hippus_amplitude_mm(lo, hi, p_max)
            if amplitude > bound:
                raise PhysicsRangeError(
                    f"hippus_amplitude_mm = {amplitude:g} mm would take a {lo:g} mm pupil out of "
                    f"(0, {p_max:g}) mm; it must be <= {bound:.4g} mm"
                )
        # The largest pupil of eq. 1 over the range of means: the window must hold it.
        means = np.linspace(lo, hi, 201)
        largest = float(np.max(means + amplitude * np.asarray(hippus_scale(means, p_max))))
        lens_radius = float(dynamics.lens.radius_mm)
        for population in eye.particles:
            if (
                population.region == "lens_nucleus"
                and float(population.region_radius_mm) > lens_radius
            ):
                raise PhysicsRangeError(
                    f"lens_nucleus particles fill a ball of {float(population.region_radius_mm):g} "
                    f"mm, larger than the lens (radius_mm = {lens_radius:g} mm)"
                )
        decentre = float(np.hypot(*np.asarray(eye.pupil.decentration_mm)))
        extent = 2.0 * (decentre + 0.5 * max(largest, float(eye.pupil.diameter_mm)))
        aperture_npix = npix // 2 if aperture_npix is None else aperture_npix
        if window_mm is None:
            window_mm = default_window_mm(extent, int(aperture_npix))
        spectrum = Spectrum.build(
            wavelengths_nm,
            spectral="scaled",
            reference_wavelength_nm=reference_wavelength_nm,
            illuminant=illuminant,
            colourspace=colourspace,
            copy_weighting=copy_weighting,
        )
        propagator = build_propagator(
            extent,
            spectrum,
            focal_length_mm=focal_length_mm,
            npix=npix,
            pixel_scale_deg=None,
            aperture_npix=aperture_npix,
            window_mm=window_mm,
            propagation="fresnel" if fresnel == "retina" else "fraunhofer",
            method="transfer" if fresnel == "retina" else "fft",
        )
        if fresnel == "effective":
            _check_effective_distance(
                propagator.grid, reference_wavelength_nm, float(fresnel_distance_mm)
            )
        # Structures finer than the raster: gratings it aliases are refused, the rest warned.
        check_structures(
            eye,
            propagator.grid,
            tuple(float(w) for w in np.asarray(spectrum.wavelengths_nm).reshape(-1)),
            None
            if fresnel == "retina"
            else math.radians(float(propagator.output.half_field_deg)),
        )
        return cls(
            eye=eye.with_stamp_windows(propagator.grid),
            dynamics=dynamics,
            key=key,
            propagator=propagator,
            spectrum=spectrum,
            field_luminance_cd_m2=field_luminance_cd_m2,
            luminance_scale=luminance_scale,
            fps=float(fps),
            lids_move=dynamics.lids.blinks,
            psf_scale_deg=float(propagator.output.pixel_scale_deg),
            brightness=brightness,
            fresnel=fresnel,
            fresnel_distance_mm=None if fresnel_distance_mm is None else float(fresnel_distance_mm),
            tonemap_name=tonemap_name,
            tonemap_params=tuple(sorted((k, float(v)) for k, v in params.items())),
        )

    # ----------------------------------------------------------------------------- basics

    def with_fps(self, fps: float) -> TemporalGlare:
        """A copy running at `fps` frames per second (checked for a stable integration)."""
        if not (isinstance(fps, int | float) and math.isfinite(fps) and fps > 0):
            raise PhysicsRangeError(f"fps must be a finite number > 0 frames/s, got {fps!r}")
        self.dynamics.check_time_step(1.0 / float(fps))
        return dataclasses.replace(self, fps=float(fps))

    @property
    def frame_s(self) -> float:
        """Duration of one frame (s)."""
        return 1.0 / self.fps

    @property
    def is_spectral(self) -> bool:
        return self.spectrum.is_spectral

    def init_state(self, field_luminance_cd_m2: ArrayLike | None = None) -> DynamicsState:
        """The eye at rest at time 0, adapted to a luminance (default: the model's)."""
        lum = self.field_luminance_cd_m2 if field_luminance_cd_m2 is None else field_luminance_cd_m2
        return self.dynamics.init_state(lum)

    def frame_values(self, state: DynamicsState) -> FrameValues:
        """The dynamics' numbers for the frame `state` is at."""
        return self.dynamics.values(state, self.key, self.eye.pupil.diameter_mm)

    def advance(
        self,
        state: DynamicsState,
        frame_luminance: ArrayLike,
        head_acceleration_rad_s2: Float[ArrayLike, " 3"] | None = None,
    ) -> DynamicsState:
        """The state one frame later, after a frame of mean luminance `frame_luminance` (cd/m^2).

        `head_acceleration_rad_s2`: the observer's angular acceleration during the frame
        (rad/s^2, ``(3,)``: x, y in the pupil plane, z along the axis), the paper's
        "observer motion" that swings the vitreous; None: a still head.
        """
        return self.dynamics.step(
            state,
            frame_luminance,
            self.frame_s,
            self.key,
            self.eye.pupil.diameter_mm,
            head_acceleration_rad_s2,
        )

    # ----------------------------------------------------------------------------- aperture

    def _depths_mm(self, index: int, population: Particles) -> Array:
        """Each moving particle's coordinate along the axis, uniform over its chord.

        A point uniform in a volume, given its projection ``(x, y)``, is uniform along the
        chord through it; lens-nucleus particles are kept inside both their ball and the
        lens spheroid.
        """
        xy = population.drawn_centers_mm()
        rho2 = jnp.sum(xy * xy, axis=-1)
        big_r = population.region_radius_mm
        half = safe_sqrt(big_r * big_r - rho2)
        if population.region == "lens_nucleus":
            half = jnp.minimum(half, self.dynamics.lens.half_height_mm(jnp.sqrt(rho2)))
        k = jax.random.fold_in(jax.random.fold_in(self.key, _DEPTH_TAG), index)
        u = uniform(k, (population.n_max,), xy.dtype)
        return (2.0 * u - 1.0) * half

    def _offsets_mm(self, population: Particles, depth_mm: Array, values: FrameValues) -> Array:
        """Displacement (mm) of each particle of a moving population in this frame."""
        xy = population.drawn_centers_mm()
        if population.region == "lens_nucleus":
            rho = jnp.sqrt(jnp.maximum(jnp.sum(xy * xy, axis=-1), 1e-30))
            new_rho, _ = self.dynamics.lens.deform(values.lens, rho, depth_mm)
            # Radial motion only: the mesh is the lens's meridional section, and the axial
            # coordinate does not survive the projection onto the pupil plane.
            return ((new_rho - rho) / rho)[:, None] * xy
        points = jnp.concatenate([xy, depth_mm[:, None]], axis=-1)
        return (points @ values.vitreous_rotation.T)[:, :2] - xy

    def frame_eye(
        self, values: FrameValues, static: SequenceConstants | None = None
    ) -> EyeAperture:
        """The eye of one frame: pupil, lids and moving particles set from `values`."""
        eye = eqx.tree_at(lambda e: e.pupil.diameter_mm, self.eye, values.pupil_mm)
        if eye.lids is not None:
            frac = values.lid_open_fraction
            eye = eqx.tree_at(
                lambda e: (e.lids.upper_opening_mm, e.lids.lower_opening_mm),
                eye,
                (self.eye.lids.upper_opening_mm * frac, self.eye.lids.lower_opening_mm * frac),
            )
        depths = self._all_depths() if static is None else static.depths_mm
        particles = list(eye.particles)
        for n, i in enumerate(self._moving_indices()):
            offsets = self._offsets_mm(particles[i], depths[n], values)
            particles[i] = dataclasses.replace(particles[i], offsets_mm=offsets)
        return dataclasses.replace(eye, particles=tuple(particles))

    def _moving_indices(self) -> tuple[int, ...]:
        return tuple(i for i, p in enumerate(self.eye.particles) if p.region in _MOVING)

    def _all_depths(self) -> tuple:
        return tuple(self._depths_mm(i, self.eye.particles[i]) for i in self._moving_indices())

    def sequence_constants(self) -> SequenceConstants:
        """Everything that does not change from frame to frame (computed once per sequence)."""
        grid = self.propagator.grid
        eye = self.eye
        moving = set(self._moving_indices())
        log_static = jnp.zeros((grid.npix, grid.npix), jnp.result_type(grid.pitch_mm, float))
        for i, population in enumerate(eye.particles):
            if i not in moving:
                log_static = log_static + population.log_transmission(grid)
        if eye.gratings is not None:
            log_static = log_static + eye.gratings.log_transmission(grid)
        # The lids' resting opening is (1 - squint) of the configured one; a frame whose open
        # fraction equals it (no blink under way) reuses this raster.
        open_fraction = (1.0 - self.dynamics.lids.squint) * (1.0 - jnp.zeros(()))
        rest = eye
        if eye.lids is not None:
            rest = eqx.tree_at(
                lambda e: (e.lids.upper_opening_mm, e.lids.lower_opening_mm),
                eye,
                (
                    eye.lids.upper_opening_mm * open_fraction,
                    eye.lids.lower_opening_mm * open_fraction,
                ),
            )
        return SequenceConstants(
            fresnel=(
                fresnel_phase(
                    grid, self.spectrum.reference_wavelength_nm, self.fresnel_distance_mm
                )
                if self.fresnel == "effective"
                else jnp.ones((), jnp.result_type(grid.pitch_mm, float))
            ),
            log_static=log_static,
            obstacle=rest.obstacle_transmission(grid),
            open_fraction=open_fraction,
            depths_mm=self._all_depths(),
        )

    def _aperture(self, static: SequenceConstants, values: FrameValues) -> Float[Array, "n n"]:
        grid = self.propagator.grid
        eye = self.frame_eye(values, static)
        log_t = static.log_static
        for i in self._moving_indices():
            log_t = log_t + eye.particles[i].log_transmission(grid)
        pupil = eye.opening(grid) * jnp.exp(log_t)
        if eye.lids is None and eye.obstacle_image is None:
            return pupil
        if not self.lids_move or eye.lids is None:
            return pupil * static.obstacle
        obstacle = jax.lax.cond(
            values.lid_open_fraction == static.open_fraction,
            lambda: static.obstacle,
            lambda: eye.obstacle_transmission(grid),
        )
        return pupil * obstacle

    def aperture(self, state: DynamicsState | None = None) -> Float[Array, "n n"]:
        """The frame's amplitude transmission ``P t_o`` on the propagator's grid."""
        state = self.init_state() if state is None else state
        return self._aperture(self.sequence_constants(), self.frame_values(state))

    # ----------------------------------------------------------------------------- PSF

    def _mono_psf(self, static: SequenceConstants, aperture: Array) -> Float[Array, "npix npix"]:
        prop = self.propagator
        # Per unit power through the aperture, measured on the real raster (the Fresnel
        # term's phase does not change it).
        area_px = open_area_px(aperture)
        if self.fresnel == "retina":
            psf = prop(
                aperture,
                self.spectrum.reference_wavelength_nm,
                open_area_mm2=area_px * prop.grid.pitch_mm**2,
            )
        elif self.fresnel == "effective":
            psf = intensity_fft(
                aperture * static.fresnel, prop.fft_npix, prop.output.npix, open_area_px=area_px
            )
        else:
            psf = intensity_fft(aperture, prop.fft_npix, prop.output.npix, open_area_px=area_px)
        if self.brightness == "transmitted":
            psf = psf * (area_px * prop.grid.pitch_mm**2)
        return psf

    def _spectral_cf(self, mono: Array) -> Float[Array, "c npix npix"]:
        """Linear RGB PSF, channels first, from scaled copies of the reference PSF."""
        if not self.is_spectral:
            return mono[None]
        spec = self.spectrum
        factors = spec.wavelengths_nm.astype(mono.dtype) / spec.reference_wavelength_nm
        weights = copy_weights(spec.weights_xyz.astype(mono.dtype), factors, spec.copy_weighting)
        return scaled_copies(mono, factors, xyz_to_rgb(weights, spec.colourspace))

    def psf_cf(
        self, static: SequenceConstants, state: DynamicsState
    ) -> Float[Array, "c npix npix"]:
        """A frame's PSF, channels first (``(1, n, n)`` mono), given the sequence constants."""
        return self._spectral_cf(
            self._mono_psf(static, self._aperture(static, self.frame_values(state)))
        )

    def psf(self, state: DynamicsState | None = None) -> Float[Array, "npix npix *c"]:
        """The PSF of one frame: ``(npix, npix, 3)`` linear RGB, or ``(npix, npix)`` mono.

        Energy per pixel at :attr:`pixel_scale_deg`, centre at ``npix // 2``: Y sums to
        the transmitted power (mm^2) with ``brightness="transmitted"``, to 1 with
        ``"unit"``. `state` defaults to :meth:`init_state`. Compiled as one program
        (run op by op, one 512² RGB frame compiled ~540 one-operation programs: 54 s of
        CPU against 29 s); inside a caller's `jit`, `vmap` or `grad` it is inlined.
        """
        return _frame_psf(self, state)

    # ------------------------------------------------------------------ the model interface

    def __call__(
        self, light_angle_deg: Float[ArrayLike, " 2"] | None = None, *, state: Any = None
    ) -> Float[Array, "npix npix *c"]:
        """A frame's PSF (see :meth:`psf`); the same for every light direction."""
        light_angle(light_angle_deg)
        return self.psf(state)

    def spot_raster(self) -> Float[Array, "n n"]:
        """The resting eye's aperture (its pupil at :attr:`field_luminance_cd_m2`)."""
        return self.aperture()

    def header(self) -> dict[str, Any]:
        header = (
            raster_header(self)
            if self.brightness == "unit"
            else raster_header(self, "transmitted power per pixel (mm^2 of the aperture)")
        )
        return {**header, "fresnelTerm": self.fresnel}

    def sized_for(self, others) -> TemporalGlare:
        return self  # the eye's windows are sized for the dynamics' range when built

    def to_config(self) -> dict[str, Any]:
        """The config of this model, every choice explicit (same key, sampling, dynamics
        and eye): ``build_model(model.to_config())`` rebuilds it."""
        prop, spec = self.propagator, self.spectrum
        table: dict[str, Any] = {
            "kind": "temporal",
            "focal_length_mm": float(prop.focal_length_mm),
            "aperture_npix": prop.grid.npix,
            "window_mm": float(prop.grid.width_mm),
            "fps": self.fps,
            "key_data": [int(v) for v in np.asarray(jax.random.key_data(self.key)).ravel()],
            "field_luminance_cd_m2": float(self.field_luminance_cd_m2),
            "luminance_scale": float(self.luminance_scale),
            "brightness": self.brightness,
            "fresnel": self.fresnel,
            "tonemap": self.tonemap_name,
            "tonemap_params": dict(self.tonemap_params),
            "eye": eye_to_config(self.eye),
            "dynamics": {
                name: _part_table(getattr(self.dynamics, name)) for name in _DYNAMICS_PARTS
            },
        }
        if self.fresnel_distance_mm is not None:
            table["fresnel_distance_mm"] = self.fresnel_distance_mm
        return {
            "model": table,
            "output": {"npix": prop.output.npix},
            "spectrum": {
                "wavelengths_nm": [float(w) for w in spec.wavelengths_nm],
                "spectral": "scaled",
                "reference_wavelength_nm": spec.reference_wavelength_nm,
                "illuminant": spec.illuminant,
                "colourspace": spec.colourspace,
                "copy_weighting": spec.copy_weighting,
            },
        }

    def psf_sequence(
        self,
        n_frames: int,
        luminance_cd_m2: Float[ArrayLike, "*n"] | None = None,
        state: DynamicsState | None = None,
        head_acceleration_rad_s2: Float[ArrayLike, "*n 3"] | None = None,
    ) -> tuple[DynamicsState, Float[Array, "n npix npix *c"]]:
        """PSFs of `n_frames` consecutive frames, by one `lax.scan`.

        **Arguments:**

        - `n_frames`: number of frames (static int >= 1).
        - `luminance_cd_m2`: mean luminance of each frame (cd/m^2), a scalar or an
          ``(n_frames,)`` array; default the model's `field_luminance_cd_m2`.
        - `state`: the first frame's state (default :meth:`init_state` adapted to the
          first frame's luminance).
        - `head_acceleration_rad_s2`: the observer's angular acceleration (rad/s^2), one
          ``(3,)`` for every frame or ``(n_frames, 3)``; default a still head.

        **Returns:** the state after the last frame, and the PSFs.
        """
        check_n_frames(n_frames)
        lum = self.field_luminance_cd_m2 if luminance_cd_m2 is None else as_float(luminance_cd_m2)
        lum = jnp.broadcast_to(lum, (n_frames,))
        state = self.init_state(lum[0]) if state is None else state
        static = self.sequence_constants()
        head = head_motion(head_acceleration_rad_s2, n_frames, lum.dtype)

        def body(s, inputs):
            frame_lum, frame_head = inputs
            cf = self.psf_cf(static, s)
            return self.advance(s, frame_lum, frame_head), cf

        state, cfs = jax.lax.scan(body, state, (lum, head))
        return state, (cfs[:, 0] if not self.is_spectral else jnp.moveaxis(cfs, 1, -1))

    def aperture_sequence(
        self,
        n_frames: int,
        luminance_cd_m2: Float[ArrayLike, "*n"] | None = None,
        state: DynamicsState | None = None,
    ) -> tuple[DynamicsState, Float[Array, "n a a"]]:
        """The apertures ``P t_o`` of `n_frames` consecutive frames, by one `lax.scan` (the
        arguments of :meth:`psf_sequence`), for a renderer that transforms them itself: the
        progressive quads of :mod:`invglare.models.quad_sequence`."""
        check_n_frames(n_frames)
        lum = self.field_luminance_cd_m2 if luminance_cd_m2 is None else as_float(luminance_cd_m2)
        lum = jnp.broadcast_to(lum, (n_frames,))
        state = self.init_state(lum[0]) if state is None else state
        static = self.sequence_constants()

        def body(s, frame_lum):
            return self.advance(s, frame_lum), self._aperture(static, self.frame_values(s))

        return jax.lax.scan(body, state, lum)


def _check_effective_distance(grid, wavelength_nm: float, distance_mm: float) -> None:
    """Refuse an effective distance whose E the raster aliases, naming the raster it needs."""
    edge_mm = 0.5 * float(grid.width_mm)
    if fresnel_chirp_aliased(grid, wavelength_nm, distance_mm, edge_mm):
        chirp = edge_mm / (wavelength_nm * 1e-6 * distance_mm)
        needed = math.ceil(2.0 * chirp * float(grid.width_mm))
        shortest = edge_mm * 2.0 * float(grid.pitch_mm) / (wavelength_nm * 1e-6)
        raise PhysicsRangeError(
            f"fresnel_distance_mm = {distance_mm:g}: E oscillates at {chirp:.4g} cycles/mm at "
            f"the window's edge ({edge_mm:g} mm), above the {0.5 / float(grid.pitch_mm):.4g} "
            f"the {grid.npix}-sample raster resolves; use aperture_npix >= {needed}, a "
            f"distance >= {shortest:.4g} mm, or fresnel = 'retina' (alias-free at any raster)"
        )


def head_motion(
    head_acceleration_rad_s2: Float[ArrayLike, "*n 3"] | None, n_frames: int, dtype
) -> Float[Array, "n 3"]:
    """Per-frame observer angular accelerations ``(n_frames, 3)`` (rad/s^2; zeros if None).

    **Raises:** `InputDataError` for another shape or non-finite values.
    """
    if head_acceleration_rad_s2 is None:
        return jnp.zeros((n_frames, 3), dtype)
    head = as_float(head_acceleration_rad_s2)
    if head.shape not in ((3,), (n_frames, 3)):
        raise InputDataError(
            f"head_acceleration_rad_s2 must have shape (3,) or ({n_frames}, 3), got {head.shape}"
        )
    if is_concrete(head) and not bool(jnp.all(jnp.isfinite(head))):
        raise InputDataError("head_acceleration_rad_s2 must be finite")
    return jnp.broadcast_to(head, (n_frames, 3)).astype(dtype)


@eqx.filter_jit
def _frame_psf(model: TemporalGlare, state: DynamicsState | None) -> Array:
    state = model.init_state() if state is None else state
    cf = model.psf_cf(model.sequence_constants(), state)
    return cf[0] if not model.is_spectral else jnp.moveaxis(cf, 0, -1)


def check_n_frames(n_frames: int) -> None:
    """Refuse a number of frames that is not a static integer >= 1 (`ConfigError`)."""
    if not isinstance(n_frames, int | np.integer) or isinstance(n_frames, bool) or n_frames < 1:
        raise ConfigError(f"n_frames must be an integer >= 1 (static), got {n_frames!r}")


# --------------------------------------------------------------------------------------
# configuration

_DYNAMICS_PARTS = ("pupil", "accommodation", "lens", "vitreous", "lids")


def _part_table(part) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for f in dataclasses.fields(part):
        value = getattr(part, f.name)
        if isinstance(value, bool | int | str):
            out[f.name] = value
        elif isinstance(value, tuple):
            out[f.name] = [float(v) for v in value]
        else:
            # float32 leaves printed at their own precision (0.03, not 0.029999999329447746).
            out[f.name] = float(
                str(np.asarray(value).item() if value.dtype == np.float64 else np.float32(value))
            )
    return out
