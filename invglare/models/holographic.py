"""The holographic layered eye of Novosad & Ziegler: a frame and its depth through thin layers.

The paper's eye simulation (sec. 2) as a model: every pixel of an HDR frame is a point
source at its reprojected position; their spherical waves meet the eye's first plane (the
base layer) and pass parallel thin layers, carried between them by the angular spectrum:

| layer        | plane (mm in front of the pupil) | transmission                          |
|--------------|----------------------------------|---------------------------------------|
| spectacles   | `spectacle_distance_mm` (15.6)   | sphere and cylinder phase             |
| lashes       | `lash_distance_mm` (8)           | lids and lashes (amplitude)           |
| tear film    | `cornea_distance_mm` (3.6)       | ``exp(i k (eta - 1) d)``, a height field |
| pupil, lens  | 0                                | pupil opening, accommodation phase    |

then the lens focuses them on the retina (one FFT: the retinal image's pixels are the
frame's directions). Each layer but the base can be switched off (`layers`); the first
active plane is the base plane. Iterations with new random phases average the speckle
away (:meth:`HolographicEye.render`); :meth:`HolographicEye.speckle_free_image` computes
their limit directly, and is the fast mode (exact when no layer is in front of the pupil;
see :mod:`invglare.optics.holographic.stack` for what it approximates otherwise).

**Sampling** (:mod:`invglare.optics.holographic.sampling`): all grids are ``N x N``; the
output pixel is ``dt`` (tangent space) and the aperture pitch of wavelength ``lambda`` is
``lambda / (N dt)``, so the window ``lambda / dt`` must hold the pupil and the sideways walk
of the light over the layers in front of it, at the shortest wavelength. A frame of
``H x W`` pixels sits at the centre of the grid (``N >= input_step * max(H, W)``), its
pixels ``input_step`` output pixels apart; the grid is periodic, so glare that leaves one
edge of the grid comes back at the other: leave a margin (``N`` larger than the frame)
where that matters. The layers themselves run on the central ``layer_npix`` samples that
the pupil's light crosses (a cropped stack: 240 of 512 for a 3 mm pupil in an 8 mm
window), the same computation as on the whole grid to float32 round-off, at a third of
the cost (:class:`~invglare.optics.holographic.ChannelStack`).

**Fittable leaves**: ``eye.pupil.diameter_mm``, ``accommodation_d`` (the lens's focus, in
dioptres: 1000 / focus distance in mm), ``tear_film.amplitude_um``,
``tear_film.scale_mm``, the lash layout (``eye.upper_lashes.*``: count, angles,
thickness, length, ...), the spectacles' powers, and the constant scene depth
``depth_mm``.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Key

from invglare._core.checks import as_float, check_static_int
from invglare.aperture.eye import EyeAperture, eye_to_config
from invglare.errors import ConfigError, InputDataError, PhysicsRangeError
from invglare.models.base import AbstractGlareModel
from invglare.optics.fourier import fft_size
from invglare.optics.holographic.layers import (
    Spectacles,
    propagation_kernel,
    thin_lens_phase,
    vergence_chirp,
)
from invglare.optics.holographic.sampling import HoloSampling, depth_layers_needed
from invglare.optics.holographic.sources import (
    PHASES,
    Frustum,
    bins_to_image,
    check_depth_buffer,
    check_frame,
    crop_frame,
    decode_depth,
    directions,
    image_to_bins,
    layer_vergences,
    place_frame,
    source_amplitudes,
)
from invglare.optics.holographic.stack import (
    ChannelStack,
    iterate_intensity,
    iteration_bytes,
    point_response,
    speckle_free,
    stack_bytes,
)
from invglare.optics.holographic.tear_film import TearFilm

__all__ = [
    "LAYERS",
    "MODES",
    "HolographicEye",
]

#: The switchable layers (the base layer is always on).
LAYERS = ("spectacles", "lashes", "tear_film", "pupil", "lens")
#: How :meth:`HolographicEye.image` renders: random-phase iterations or their limit.
MODES = ("iterations", "speckle_free")
#: Default wavelengths of the R, G and B channels (nm).
DEFAULT_RGB_NM = (640.0, 550.0, 460.0)
#: Pixels of margin kept between the light the pupil needs and the window's edge.
_MARGIN_PX = 2
#: Width (px) of the smooth taper at the edge of a cropped stack's grid.
TAPER_PX = 12


def crop_taper(m: int, taper_px: int) -> np.ndarray:
    """A separable raised-cosine window: 1 inside, falling to 0 over `taper_px` at each edge.

    Centred layout (like the rasters). Smooth, so the cropped field has no edge to diffract
    from; the light the pupil receives never crosses the taper.
    """
    i = np.arange(m)
    edge = np.minimum(i, m - 1 - i).astype(float)
    w = np.where(edge >= taper_px, 1.0, np.sin(0.5 * np.pi * (edge + 0.5) / taper_px) ** 2)
    return np.outer(w, w)


def _concrete(*xs) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in xs)


def check_iterations(iterations) -> int:
    """Refuse a number of iterations that is not an integer >= 1 (`ConfigError`)."""
    if not isinstance(iterations, int | np.integer) or isinstance(iterations, bool):
        raise ConfigError(f"iterations must be an integer >= 1, got {iterations!r}")
    if iterations < 1:
        raise ConfigError(
            f"iterations must be >= 1 (one random-phase draw at least), got {iterations}"
        )
    return int(iterations)


def _check_angle(angle: Array, batched: bool) -> None:
    """Light directions ``(2,)`` or ``(K, 2)`` (x, y deg); concrete ones finite, within 90 deg."""
    expected = "(K, 2)" if batched else "(2,)"
    if angle.ndim != (2 if batched else 1) or angle.shape[-1] != 2:
        raise PhysicsRangeError(
            f"light_angle_deg must have shape {expected} (x, y angles in deg), got {angle.shape}"
        )
    if _concrete(angle):
        arr = np.asarray(angle, dtype=float)
        if not np.all(np.isfinite(arr)) or np.any(np.abs(arr) >= 90.0):
            raise PhysicsRangeError(
                f"light_angle_deg must be finite and within (-90, 90) deg, got {arr.tolist()}"
            )


def focus_to_accommodation_d(focus_distance_mm: float) -> float:
    """Accommodation (D) of an eye focused at `focus_distance_mm` (> 0; ``inf``: 0 D)."""
    f = float(focus_distance_mm)
    if not (f > 0) or math.isnan(f):
        raise PhysicsRangeError(f"focus distance must be > 0 (inf for a relaxed eye), got {f:g} mm")
    return 0.0 if math.isinf(f) else 1000.0 / f


class HolographicEye(AbstractGlareModel):
    """The holographic layered eye: frame + depth -> point sources -> thin layers -> retina.

    Build one with :meth:`build` (validated) or from a config with
    :func:`holographic_from_config`.

    **Fields (leaves):**

    - `eye`: an :class:`~invglare.aperture.eye.EyeAperture`: its pupil (and particles and
      gratings, which sit in the pupil plane) is the pupil layer, its lids and lashes the
      lash layer.
    - `accommodation_d`: the lens's focus (D, ``1000 / focus distance in mm``).
    - `depth_mm`: the scene's depth (mm) when no depth buffer is given.
    - `tear_film`: a :class:`~invglare.optics.holographic.TearFilm` or None.
    - `spectacles`: a :class:`~invglare.optics.holographic.Spectacles` or None.

    **Configuration (static):** `sampling`, `frustum`, `layers` (the active switchable
    layers), the planes' distances, `depth_layers`, `iterations`, `input_step`,
    `phases`, `chunk` (iterations per batch, from the memory budget), `psf_tiles`
    (speckle-free mode), `mode`.

    **Example:**

    ```python
    model = HolographicEye.build(eye, npix=256, window_mm=8.0, focus_distance_mm=2000.0)
    img = model.render(frame, key=jax.random.key(0), iterations=16)   # (H, W, 3)
    limit = model.speckle_free_image(frame)                             # the same, n -> inf
    ```
    """

    #: The model interface's class variables: a PSF centred on the light's image; static.
    centre: ClassVar[str] = "light"
    animated: ClassVar[bool] = False
    renders_scenes: ClassVar[bool] = True

    eye: EyeAperture
    accommodation_d: Float[Array, ""] = eqx.field(converter=as_float)
    depth_mm: Float[Array, ""] = eqx.field(converter=as_float)
    tear_film: TearFilm | None
    spectacles: Spectacles | None
    sampling: HoloSampling
    frustum: Frustum
    layers: tuple[str, ...] = eqx.field(static=True)
    lash_distance_mm: float = eqx.field(static=True, default=8.0)
    cornea_distance_mm: float = eqx.field(static=True, default=3.6)
    spectacle_distance_mm: float = eqx.field(static=True, default=15.6)
    depth_layers: int = eqx.field(static=True, default=1)
    iterations: int = eqx.field(static=True, default=16)
    input_step: int = eqx.field(static=True, default=1)
    phases: str = eqx.field(static=True, default="uniform")
    chunk: int = eqx.field(static=True, default=8)
    psf_tiles: int = eqx.field(static=True, default=1)
    mode: str = eqx.field(static=True, default="iterations")
    memory_budget_mb: float = eqx.field(static=True, default=1024.0)
    max_pupil_mm: float | None = eqx.field(static=True, default=None)
    layer_npix: int = eqx.field(static=True, default=0)

    # ------------------------------------------------------------------ build

    @classmethod
    def build(
        cls,
        eye: EyeAperture,
        *,
        npix: int = 512,
        window_mm: float | None = 8.0,
        pixel_scale_deg: float | None = None,
        wavelengths_nm: Any = DEFAULT_RGB_NM,
        focus_distance_mm: float = math.inf,
        depth_mm: float = 2000.0,
        tear_film: TearFilm | None = None,
        spectacles: Spectacles | None = None,
        layers: Any = ("lashes", "tear_film", "pupil", "lens"),
        frustum: Frustum | None = None,
        lash_distance_mm: float = 8.0,
        cornea_distance_mm: float = 3.6,
        spectacle_distance_mm: float = 15.6,
        depth_layers: int | str = 1,
        iterations: int = 16,
        input_step: int = 1,
        phases: str = "uniform",
        psf_tiles: int = 1,
        mode: str = "iterations",
        memory_budget_mb: float = 1024.0,
        chunk: int | None = None,
        max_pupil_mm: float | None = None,
        layer_npix: int | None = None,
    ) -> HolographicEye:
        """Choose the sampling and check every choice before any work.

        **Arguments:**

        - `eye`: pupil (required), lids and lashes (the lash layer), particles.
        - `npix`: grid size ``N`` (even).
        - `window_mm` or `pixel_scale_deg`: the aperture window of the shortest wavelength
          (mm), or the output pixel (deg); give one (`pixel_scale_deg` wins).
        - `wavelengths_nm`: one per channel (default R, G, B = 640, 550, 460 nm).
        - `focus_distance_mm`: where the lens focuses (mm, > 0; ``inf``: relaxed).
        - `depth_mm`: the scene's depth without a depth buffer (mm, > 0).
        - `tear_film`, `spectacles`: the layers' elements (None: not present).
        - `layers`: the switchable layers that are on (of :data:`LAYERS`).
        - `frustum`: how depth buffers are decoded (default: planar depth in metres).
        - `lash_distance_mm`, `cornea_distance_mm`, `spectacle_distance_mm`: the planes.
        - `depth_layers`: vergence layers (int >= 1) or ``"auto"`` (from the frustum's
          near and far planes, the largest pupil and the shortest wavelength, with
          :func:`~invglare.optics.holographic.depth_layers_needed`).
        - `iterations`: default random-phase draws of :meth:`render` (>= 1).
        - `input_step`: output pixels between two input pixels (>= 1).
        - `phases`: ``"uniform"`` or ``"quaternary"``.
        - `psf_tiles`: PSF tiles per axis of the speckle-free mode.
        - `mode`: what :meth:`image` does by default (:data:`MODES`).
        - `memory_budget_mb`: working memory of a batch of iterations (MB).
        - `chunk`: iterations propagated at once (default: 1 on a CPU, else as many as
          the budget holds, at most 32), capped by the budget.
        - `max_pupil_mm`: the largest pupil the model will be given (a fit's upper
          bound); default the eye's. The window is checked for it.
        - `layer_npix`: the layers' grid ``m <= N`` (a cropped stack, see
          :class:`~invglare.optics.holographic.ChannelStack`); default the smallest fast
          size that holds the pupil's light and a taper of :data:`TAPER_PX` (``N`` with
          spectacles on); ``N`` runs the layers on the whole grid.

        **Raises:** `ConfigError` for bad choices; `PhysicsRangeError` for a focus distance
        <= 0, a window too small for the pupil, a lens or tear film the grid aliases.
        """
        if not isinstance(eye, EyeAperture):
            raise ConfigError(f"the holographic eye needs an EyeAperture, got {type(eye).__name__}")
        if pixel_scale_deg is not None:
            sampling = HoloSampling.from_pixel_scale(npix, pixel_scale_deg, wavelengths_nm)
        elif window_mm is not None:
            sampling = HoloSampling.from_window(npix, window_mm, wavelengths_nm)
        else:
            raise ConfigError("give window_mm or pixel_scale_deg")
        layers = tuple(layers)
        for name in layers:
            if name not in LAYERS:
                raise ConfigError(f"layer {name!r} is not one of {', '.join(LAYERS)}")
        layers = tuple(name for name in LAYERS if name in layers)
        frustum = Frustum() if frustum is None else frustum
        if not isinstance(frustum, Frustum):
            raise ConfigError(f"frustum must be a Frustum, got {type(frustum).__name__}")
        for name, value in (
            ("lash_distance_mm", lash_distance_mm),
            ("cornea_distance_mm", cornea_distance_mm),
            ("spectacle_distance_mm", spectacle_distance_mm),
        ):
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise PhysicsRangeError(f"{name} must be a finite number > 0 mm, got {value!r}")
        if phases not in PHASES:
            raise ConfigError(f"phases = {phases!r} is not one of {', '.join(PHASES)}")
        if mode not in MODES:
            raise ConfigError(f"mode = {mode!r} is not one of {', '.join(MODES)}")
        iterations = check_iterations(iterations)
        input_step = check_static_int("input_step", input_step, 1)
        psf_tiles = check_static_int("psf_tiles", psf_tiles, 1)
        accommodation = focus_to_accommodation_d(focus_distance_mm)
        if not (isinstance(depth_mm, int | float) and math.isfinite(depth_mm) and depth_mm > 0):
            raise PhysicsRangeError(f"depth_mm must be a finite depth > 0 mm, got {depth_mm!r}")
        pupil_mm = float(eye.pupil.diameter_mm) if max_pupil_mm is None else float(max_pupil_mm)
        if depth_layers == "auto":
            if frustum.near_mm is None:
                raise ConfigError("depth_layers = 'auto' needs the frustum's near_mm")
            far = math.inf if frustum.far_mm is None else frustum.far_mm
            depth_layers = depth_layers_needed(
                frustum.near_mm, far, pupil_mm, min(sampling.wavelengths_nm)
            )
        depth_layers = check_static_int("depth_layers", depth_layers, 1)
        if not (math.isfinite(memory_budget_mb) and memory_budget_mb > 0):
            raise ConfigError(f"memory_budget_mb must be > 0, got {memory_budget_mb!r}")
        per_iteration = iteration_bytes(npix, sampling.n_channels, depth_layers)
        fixed = stack_bytes(npix, sampling.n_channels, depth_layers, 3)
        budget = memory_budget_mb * 2**20
        if fixed + per_iteration > budget:
            raise ConfigError(
                f"a {npix}^2 grid with {sampling.n_channels} channels and {depth_layers} depth "
                f"layer(s) needs about {(fixed + per_iteration) / 2**20:.0f} MB (the layers' "
                f"arrays and one iteration), above memory_budget_mb = {memory_budget_mb:g}; "
                "raise the budget or lower npix"
            )
        if chunk is None:
            # On a CPU one draw at a time is fastest (its fields stay in cache; measured at
            # 512^2: 5.0-5.6 s for 64 draws one by one against 8.3-10 s eight at a time);
            # accelerators want batches as large as the budget allows.
            chunk = 1 if jax.default_backend() == "cpu" else 32
        chunk = check_static_int("chunk", chunk, 1)
        chunk = max(1, min(chunk, iterations, int((budget - fixed) // per_iteration)))
        grid = sampling.grid(min(sampling.wavelengths_nm))
        eye = eye.with_stamp_windows(grid)
        model = cls(
            eye=eye,
            accommodation_d=accommodation,
            depth_mm=float(depth_mm),
            tear_film=tear_film,
            spectacles=spectacles,
            sampling=sampling,
            frustum=frustum,
            layers=layers,
            lash_distance_mm=float(lash_distance_mm),
            cornea_distance_mm=float(cornea_distance_mm),
            spectacle_distance_mm=float(spectacle_distance_mm),
            depth_layers=depth_layers,
            iterations=iterations,
            input_step=input_step,
            phases=phases,
            chunk=chunk,
            psf_tiles=psf_tiles,
            mode=mode,
            memory_budget_mb=float(memory_budget_mb),
            max_pupil_mm=pupil_mm,
            layer_npix=npix,
        )
        need_px = 2 * (math.ceil(model._need_radius_mm(pupil_mm) / sampling.finest_pitch_mm))
        least = need_px + 2 * TAPER_PX
        if layer_npix is None:
            # Cropped by default; not with spectacles, whose phase the crop reproduces only to
            # 5e-5-8e-4 of the PSF's peak (measured for -0.5 D at 15.6 mm; 3e-6 without).
            with_glasses = "spectacles" in layers and spectacles is not None
            layer_npix = npix if with_glasses else min(npix, fft_size(least, even=True))
        layer_npix = check_static_int("layer_npix", layer_npix, 8)
        if layer_npix > npix or (layer_npix < npix and layer_npix < least):
            raise PhysicsRangeError(
                f"layer_npix = {layer_npix} must be <= npix = {npix} and, when smaller, hold "
                f"the pupil's light and the taper: >= {least}"
            )
        model = dataclasses.replace(model, layer_npix=layer_npix)
        model.check_sampling(pupil_mm)
        return model

    # ------------------------------------------------------------------ geometry

    def _planes(self) -> list[tuple[str, float]]:
        """The active planes in front of the pupil, farthest first: (layer, distance mm)."""
        planes = []
        if "spectacles" in self.layers and self.spectacles is not None:
            planes.append(("spectacles", self.spectacle_distance_mm))
        if "lashes" in self.layers and self.eye.lids is not None:
            planes.append(("lashes", self.lash_distance_mm))
        if "tear_film" in self.layers and self.tear_film is not None:
            planes.append(("tear_film", self.cornea_distance_mm))
        return sorted(planes, key=lambda p: -p[1])

    @property
    def base_distance_mm(self) -> float:
        """Distance of the base plane (the first active plane) in front of the pupil (mm)."""
        planes = self._planes()
        return planes[0][1] if planes else 0.0

    @property
    def shift_invariant(self) -> bool:
        """Whether one PSF renders the image: no active layer in front of the pupil."""
        return not self._planes()

    @property
    def pixel_scale_deg(self) -> float:
        return self.sampling.pixel_scale_deg

    @property
    def wavelengths_nm(self) -> tuple[float, ...]:
        return self.sampling.wavelengths_nm

    @property
    def npix(self) -> int:
        return self.sampling.npix

    def _need_radius_mm(self, pupil_mm: float) -> float:
        """Radius (mm) of the disk the light reaching the pupil crosses, plus a margin."""
        dec = self.eye.pupil.decentration_mm
        decentre = float(np.hypot(*np.asarray(dec))) if _concrete(dec) else 0.0
        walk = self.base_distance_mm * self.sampling.half_field_rad
        return 0.5 * pupil_mm + decentre + walk + _MARGIN_PX * self.sampling.finest_pitch_mm

    def nearest_depth_mm(self, pupil_mm: float | None = None) -> float:
        """The nearest source depth (mm) whose wave the grid samples where it matters.

        A source at depth ``z`` reaches the base plane (``d`` in front of the pupil) with
        vergence ``1 / (z - d)``; out to the radius ``r`` the pupil's light crosses, its
        curvature bends rays by up to ``r / (z - d)``, which must stay within the grid's
        half field ``N dt / 2``: ``z >= d + r / (N dt / 2)``.
        """
        pupil = self._pupil_bound_mm() if pupil_mm is None else pupil_mm
        return self.base_distance_mm + self._need_radius_mm(pupil) / self.sampling.half_field_rad

    def _pupil_bound_mm(self) -> float:
        """The largest pupil to check for: `max_pupil_mm`, or the eye's when concrete and larger."""
        bound = 0.0 if self.max_pupil_mm is None else self.max_pupil_mm
        if _concrete(self.eye.pupil.diameter_mm):
            bound = max(bound, float(self.eye.pupil.diameter_mm))
        return bound

    def check_sampling(self, pupil_mm: float | None = None, time_s=(0.0,)) -> None:
        """Refuse a window that cannot hold the pupil, or a layer the grid aliases."""
        pupil = self._pupil_bound_mm() if pupil_mm is None else float(pupil_mm)
        s = self.sampling
        need = self._need_radius_mm(pupil)
        window = s.smallest_window_mm
        if 2.0 * need > window:
            raise PhysicsRangeError(
                f"the pupil ({pupil:g} mm) and the light's walk over the "
                f"{self.base_distance_mm:g} mm of layers in front of it need a window of "
                f"{2 * need:.3g} mm at {min(s.wavelengths_nm):g} nm; the grid's is {window:.3g} "
                "mm (window_mm = lambda / dt): use a larger window_mm (or a smaller "
                "pixel_scale_deg), and raise npix to keep the field"
            )
        half = s.half_field_rad
        if "lens" in self.layers and _concrete(self.accommodation_d):
            a = abs(float(self.accommodation_d)) * 1e-3
            radius = 0.5 * pupil
            if a * radius > half:
                raise PhysicsRangeError(
                    f"a lens accommodated by {float(self.accommodation_d):g} D (focus at "
                    f"{1000 / float(self.accommodation_d):.4g} mm) bends rays at the pupil's edge "
                    f"by {a * radius:.3g} rad, beyond the grid's half field {half:.3g} rad "
                    f"(N dt / 2): the grid aliases its phase; focus farther than "
                    f"{radius / half:.4g} mm or raise npix"
                )
        if "spectacles" in self.layers and self.spectacles is not None:
            if _concrete(self.spectacles.sphere_d, self.spectacles.cylinder_d):
                p = self.spectacles.max_power_d() * 1e-3
                radius = (
                    0.5 * pupil + self.spectacle_distance_mm * half + _MARGIN_PX * s.finest_pitch_mm
                )
                if p * radius > half:
                    raise PhysicsRangeError(
                        f"spectacles of {self.spectacles.max_power_d():g} D bend rays at "
                        f"{radius:.3g} mm by {p * radius:.3g} rad, beyond the grid's half field "
                        f"{half:.3g} rad: the grid aliases their phase; raise npix"
                    )
        film = self.tear_film
        if "tear_film" in self.layers and film is not None and _concrete(*jax.tree.leaves(film)):
            lam = min(s.wavelengths_nm)
            walk = self.cornea_distance_mm * half
            self.tear_film.check_sampled(
                s.grid(lam), lam, time_s, radius_mm=0.5 * pupil + walk + 2 * s.finest_pitch_mm
            )

    # ------------------------------------------------------------------ the stack

    def channel_stack(
        self,
        wavelength_nm: Float[ArrayLike, ""],
        vergences_per_mm: Float[ArrayLike, " l"],
        time_s: Float[ArrayLike, ""] = 0.0,
    ) -> ChannelStack:
        """The layer stack of one wavelength (traced, so `vmap` runs it over channels).

        `vergences_per_mm` are the depth layers' ``1 / z`` (z from the pupil, mm).
        """
        from invglare._core.grids import ApertureGrid

        lam = as_float(wavelength_nm)
        n, m = self.npix, self.layer_npix
        # The layers' grid: the central m x m samples of the channel's N x N grid.
        grid = ApertureGrid(m, lam * 1e-6 / (n * self.sampling.pixel_scale_rad))

        def element(name: str):
            if name == "spectacles":
                return self.spectacles.transmission(grid, lam)
            if name == "lashes":
                return self.eye.obstacle_transmission(grid)
            return self.tear_film.transmission(grid, lam, time_s)

        opening = self.eye.pupil.coverage(grid)
        if "pupil" in self.layers:
            last = self.eye.pupil_transmission(grid)
            # The clear pupil's share of the N x N window (the crop holds all of it).
            gain = n * n / jnp.sum(opening)
        else:
            last = jnp.ones_like(opening)
            gain = jnp.ones((), opening.dtype)
        if "lens" in self.layers:
            last = last * thin_lens_phase(grid, lam, self.accommodation_d * 1e-3)
        planes = self._planes()
        d_base = planes[0][1] if planes else 0.0
        v = jnp.asarray(vergences_per_mm)
        # 1 / (z - d) = V / (1 - V d): the vergence at the base plane.
        v_base = v / (1.0 - v * d_base)
        chirps = jax.vmap(lambda vl: vergence_chirp(grid, lam, vl))(v_base)
        if planes:
            first = element(planes[0][0])
            transmissions = [element(name) for name, _ in planes[1:]] + [last]
            distances = [d for _, d in planes] + [0.0]
            kernels = tuple(
                propagation_kernel(grid, lam, d0 - d1) for d0, d1 in itertools.pairwise(distances)
            )
        else:
            first, transmissions, kernels = last, [], ()
        if m < n:
            first = first * crop_taper(m, TAPER_PX)
        front = chirps * first[None]
        trans = tuple(t.astype(front.dtype) for t in transmissions)
        return ChannelStack(front, kernels, trans, gain, n)

    def stacks(self, vergences_per_mm, time_s=0.0) -> ChannelStack:
        """Every channel's stack (leading channel axis)."""
        lams = jnp.asarray(self.sampling.wavelengths_nm, jnp.result_type(float))
        return jax.vmap(lambda w: self.channel_stack(w, vergences_per_mm, time_s))(lams)

    # ------------------------------------------------------------------ sources

    def _validate(self, frame, depth, time_s) -> None:
        """Check a frame, its depth and the time before any work (concrete values only).

        **Raises:** `InputDataError` for a bad frame or depth buffer (shape, values, channel
        count, field of view), `PhysicsRangeError` for a constant depth <= 0, a source
        nearer than the grid resolves, or a tear film that aliases at `time_s`.
        """
        arr = check_frame(frame)
        shape = np.shape(frame) if arr is None else arr.shape
        if len(shape) not in (2, 3):
            raise InputDataError(f"frame must have shape (H, W) or (H, W, C), got {shape}")
        c = 1 if len(shape) == 2 else shape[-1]
        n_ch = self.sampling.n_channels
        if c not in (1, n_ch):
            raise InputDataError(
                f"the frame has {c} channels (shape {tuple(shape)}) but the eye has {n_ch} "
                f"wavelengths {self.sampling.wavelengths_nm}; give a mono frame or {n_ch} channels"
            )
        h, w = shape[:2]
        step, n = self.input_step, self.npix
        if step * h > n or step * w > n:
            raise InputDataError(
                f"a {h} x {w} frame with input step {step} needs a grid of at least "
                f"{step * max(h, w)} px; the eye's grid is {n} px"
            )
        if self.frustum.fov_x_deg is not None:
            frame_dt = self.frustum.pixel_scale_rad(w)
            want = step * self.sampling.pixel_scale_rad
            if abs(frame_dt / want - 1.0) > 1e-3:
                raise InputDataError(
                    f"the frame's field of view ({self.frustum.fov_x_deg:g} deg over {w} px, "
                    f"{math.degrees(frame_dt):.4g} deg per pixel) does not match the eye's "
                    f"{math.degrees(want):.4g} deg per input pixel (pixel_scale_deg "
                    f"{self.pixel_scale_deg:.4g} x input_step {step}); resample the frame"
                )
        z_near = None
        if depth is None:
            if _concrete(self.depth_mm):
                z_near = float(self.depth_mm)
        elif np.ndim(depth) == 0:
            if _concrete(depth):
                z_near = float(depth)
                if not (z_near > 0 and math.isfinite(z_near)):
                    raise PhysicsRangeError(f"constant depth must be > 0 mm, got {z_near!r}")
        else:
            buf = check_depth_buffer(depth, (h, w), self.frustum)
            if buf is not None and arr is not None:
                ty, tx = directions(n, self.sampling.pixel_scale_rad)
                d = place_frame(jnp.asarray(buf, jnp.float32)[None], n, step)[0]
                z = np.asarray(decode_depth(d, self.frustum, (ty, tx)))
                lit = (
                    np.asarray(
                        place_frame(jnp.asarray(arr.reshape(h, w, -1).sum(-1))[None], n, step)[0]
                    )
                    > 0
                )
                if lit.any():
                    z_near = float(z[lit].min())
        if z_near is not None:
            nearest = self.nearest_depth_mm()
            if z_near < nearest:
                raise PhysicsRangeError(
                    f"a source at {z_near:.4g} mm is nearer than this grid resolves "
                    f"({nearest:.4g} mm: its wave's curvature aliases where the pupil's "
                    "light crosses the window); raise npix or move the near plane out"
                )
        if "tear_film" in self.layers and self.tear_film is not None and _concrete(time_s):
            self.check_sampling(time_s=(float(time_s),))

    def _sources(self, frame, depth):
        """Amplitudes at their bins, the depth layers' vergences and each bin's layer (jittable)."""
        img = as_float(frame)
        img = img[None] if img.ndim == 2 else jnp.moveaxis(img, -1, 0)
        n_ch = self.sampling.n_channels
        img = jnp.broadcast_to(img, (n_ch, *img.shape[1:]))
        step, n = self.input_step, self.npix
        placed = place_frame(source_amplitudes(img, step), n, step)
        if depth is None:
            z = jnp.broadcast_to(self.depth_mm, (n, n)).astype(placed.dtype)
        elif jnp.ndim(depth) == 0:
            z = jnp.broadcast_to(as_float(depth), (n, n)).astype(placed.dtype)
        else:
            ty, tx = directions(n, self.sampling.pixel_scale_rad, placed.dtype)
            d = as_float(depth)
            d = d[..., 0] if d.ndim == 3 else d
            d_placed = place_frame(d[None], n, step)[0]
            z_all = decode_depth(d_placed, self.frustum, (ty, tx))
            # Bins without a source get a harmless depth (they carry no light).
            z = jnp.where(placed[0] > 0, z_all, jnp.max(z_all))
        vergence = 1.0 / z
        weight = jnp.sum(placed, axis=0)
        if self.depth_layers == 1 and depth is not None and jnp.ndim(depth) != 0:
            # One layer for a varying depth: the mid-range vergence.
            centres, _ = layer_vergences(vergence, weight, 1)
            index = None
        elif self.depth_layers == 1:
            centres, index = vergence[:1, 0], None
        else:
            centres, idx = layer_vergences(vergence, weight, self.depth_layers)
            index = image_to_bins(idx)
        return image_to_bins(placed), centres, index

    # ------------------------------------------------------------------ rendering

    def render(
        self,
        frame: Float[ArrayLike, "H W *c"],
        depth: Float[ArrayLike, "H W"] | float | None = None,
        key: Key[Array, ""] | int = 0,
        *,
        iterations: int | None = None,
        time_s: float | Float[ArrayLike, ""] = 0.0,
        progress: bool = False,
    ) -> Float[Array, "h w c"]:
        """Render a frame through the eye by random-phase iterations (the paper's method).

        **Arguments:**

        - `frame`: ``(H, W)`` or ``(H, W, C)`` linear HDR values (>= 0), ``C`` = channels.
        - `depth`: a depth buffer ``(H, W)`` (decoded with the frustum), one constant depth
          (mm), or None (the model's `depth_mm`).
        - `key`: key (or int seed) of the random phases.
        - `iterations`: draws to average (default the model's).
        - `time_s`: time since the last blink (the tear film's animation).
        - `progress`: a progress bar over the iterations (not under `jit`).

        **Returns:** ``(input_step H, input_step W, C)`` linear intensities at the model's
        pixel scale, in the frame's units (a clear pupil keeps the frame's brightness).

        **Raises:** `InputDataError` / `PhysicsRangeError` / `ConfigError` (see
        :meth:`check_sampling` and :func:`~invglare.optics.holographic.sources.check_depth_buffer`).

        **Example:**

        ```python
        img = model.render(frame, depth_m, key=jax.random.key(0), iterations=64)
        ```
        """
        n_it = self.iterations if iterations is None else check_iterations(iterations)
        if isinstance(key, int | np.integer):
            key = jax.random.key(int(key))
        self._validate(frame, depth, time_s)
        depth = depth if depth is None or np.ndim(depth) else as_float(depth)
        if progress:
            amps, vergences, index = self._sources(frame, depth)
            mean = iterate_intensity(
                amps, self.stacks(vergences, time_s), key, n_it, layer_index=index,
                phases=self.phases, chunk=self.chunk, progress=True,
            )  # fmt: skip
            return self._to_image(mean, np.shape(frame)[:2])
        return _render(self, frame, depth, key, n_it, as_float(time_s))

    def speckle_free_image(
        self,
        frame: Float[ArrayLike, "H W *c"],
        depth: Float[ArrayLike, "H W"] | float | None = None,
        *,
        time_s: float | Float[ArrayLike, ""] = 0.0,
        tiles: int | None = None,
    ) -> Float[Array, "h w c"]:
        """The limit of :meth:`render` over infinitely many iterations, computed directly.

        Exact when no layer is in front of the pupil (:attr:`shift_invariant`); otherwise
        exact PSFs at the centres of `tiles` x `tiles` tiles (default `psf_tiles`) of the
        frame, blended bilinearly. Same arguments and output as :meth:`render`.
        """
        tiles = self.psf_tiles if tiles is None else check_static_int("tiles", tiles, 1)
        self._validate(frame, depth, time_s)
        depth = depth if depth is None or np.ndim(depth) else as_float(depth)
        return _speckle_free(self, frame, depth, as_float(time_s), tiles)

    def _speckle_free_core(self, frame, depth, time_s, tiles: int) -> Array:
        amps, vergences, index = self._sources(frame, depth)
        stacks = self.stacks(vergences, time_s)
        h, w = np.shape(frame)[:2]
        step, n = self.input_step, self.npix
        r0, c0 = (n - step * h) // 2, (n - step * w) // 2
        mean = speckle_free(
            amps * amps,
            stacks,
            layer_index=index,
            tiles=1 if self.shift_invariant else tiles,
            region=(r0, r0 + step * h, c0, c0 + step * w),
            to_bins=lambda x: np.asarray(image_to_bins(np.asarray(x))),
        )
        return self._to_image(mean, (h, w))

    def _render_core(self, frame, depth, key, iterations: int, time_s) -> Array:
        amps, vergences, index = self._sources(frame, depth)
        mean = iterate_intensity(
            amps, self.stacks(vergences, time_s), key, iterations, layer_index=index,
            phases=self.phases, chunk=self.chunk,
        )  # fmt: skip
        return self._to_image(mean, np.shape(frame)[:2])

    def render_scene(self, frame, depth=None, key=0, *, iterations=None, progress=False):
        """A scene through the eye (the model interface's whole-scene render): :meth:`image`
        in the model's mode, with `iterations` random-phase draws where it iterates."""
        if self.mode == "speckle_free":
            return self.speckle_free_image(frame, depth)
        return self.render(frame, depth, key, iterations=iterations, progress=progress)

    def image(self, frame, depth=None, key=0, *, time_s=0.0, **kwargs) -> Array:
        """:meth:`render` or :meth:`speckle_free_image`, as the model's `mode` says."""
        if self.mode == "speckle_free":
            return self.speckle_free_image(frame, depth, time_s=time_s, **kwargs)
        return self.render(frame, depth, key, time_s=time_s, **kwargs)

    def _to_image(self, bins_cf: Array, shape: tuple[int, int]) -> Array:
        img = crop_frame(bins_to_image(bins_cf), shape, self.input_step)
        return jnp.moveaxis(img, 0, -1)

    # ------------------------------------------------------------------ PSF

    def psf(
        self,
        light_angle_deg: Float[ArrayLike, " 2"] | None = None,
        *,
        depth_mm: Float[ArrayLike, ""] | None = None,
        time_s: Float[ArrayLike, ""] = 0.0,
    ) -> Float[Array, "n n *c"]:
        """The speckle-free PSF of a point source: ``(N, N, C)``, or ``(N, N)`` with one channel.

        **Arguments:**

        - `light_angle_deg`: the source's direction ``(x, y)`` in degrees (x to the right,
          y up), rounded to the nearest output pixel; None: on the axis. With layers in
          front of the pupil the PSF depends on it.
        - `depth_mm`: the source's depth (default the model's `depth_mm`).
        - `time_s`: time since the last blink (tear film).

        **Returns:** energy per output pixel, centred on pixel ``(N // 2, N // 2)`` whatever
        the direction (the image of the source moved to the centre), unit energy for a
        clear pupil (less the light the grid's band does not hold).
        """
        return _psf(
            self,
            None if light_angle_deg is None else as_float(light_angle_deg),
            self.depth_mm if depth_mm is None else as_float(depth_mm),
            as_float(time_s),
        )

    def _psf_core(self, light_angle_deg, depth_mm, time_s) -> Array:
        n = self.npix
        stacks = self.stacks(jnp.reshape(1.0 / depth_mm, (1,)), time_s)
        if light_angle_deg is None:
            bin_yx: Any = (0, 0)
        else:
            dt = self.sampling.pixel_scale_rad
            col = jnp.round(jnp.tan(jnp.deg2rad(light_angle_deg[0])) / dt).astype(jnp.int32)
            row = jnp.round(jnp.tan(jnp.deg2rad(light_angle_deg[1])) / dt).astype(jnp.int32)
            # Image column c -> frequency column -c; image row up (-) -> frequency row -r.
            bin_yx = ((-row) % n, (-col) % n)
        psf = jax.vmap(lambda s: point_response(s, bin_yx))(stacks)
        out = jnp.moveaxis(bins_to_image(psf), 0, -1)
        return out[..., 0] if out.shape[-1] == 1 else out

    def __call__(
        self, light_angle_deg: Float[ArrayLike, " 2"] | None = None, *, state: Any = None
    ) -> Array:
        """The speckle-free PSF of a light at `light_angle_deg` (:meth:`psf`).

        The model interface's call: ``(N, N)`` for one wavelength, ``(N, N, C)`` otherwise,
        centred on the light's own image point. The model is static (`state` must be None;
        the tear film's time is :meth:`psf`'s `time_s`).
        """
        if state is not None:
            raise ConfigError(
                "HolographicEye is a static model and takes no state; give the tear film's "
                "time to psf(time_s=...) or render(time_s=...)"
            )
        if light_angle_deg is not None:
            _check_angle(as_float(light_angle_deg), batched=False)
        return self.psf(light_angle_deg)

    def batch(
        self, light_angles_deg: Float[ArrayLike, "K 2"], batch_size: int | None = None
    ) -> Array:
        """PSFs of many lights ``(K, N, N[, C])``; one PSF repeated when shift-invariant."""
        angles = as_float(light_angles_deg)
        _check_angle(angles, batched=True)
        if self.shift_invariant:
            one = self.psf()
            return jnp.broadcast_to(one, (angles.shape[0], *one.shape))
        if batch_size is None:
            return jax.vmap(self.psf)(angles)
        return jax.lax.map(self.psf, angles, batch_size=int(batch_size))

    def core_radius_px(self) -> float | None:
        """Radius (output pixels) of the Airy core, ``1.22 lambda / D``, at the longest lambda."""
        d = self.eye.pupil.diameter_mm
        if not _concrete(d):
            return None
        return 1.22 * max(self.wavelengths_nm) * 1e-6 / float(d) / self.sampling.pixel_scale_rad

    def header(self) -> dict[str, Any]:
        """Plain values describing the PSF and images for a file header."""
        return {
            "method": "holographic layered eye (Novosad & Ziegler)",
            "normalisation": "energy per pixel; unit energy through a clear pupil, less the "
            "light beyond the grid's band",
            "layers": list(self.layers),
            "iterations": self.iterations,
            "mode": self.mode,
            "depthLayers": self.depth_layers,
            "accommodationD": float(self.accommodation_d)
            if _concrete(self.accommodation_d)
            else None,
        }

    def sized_for(self, others) -> HolographicEye:
        """A copy whose lash stamp windows, window check and crop hold `others` too.

        `others` are the same model at other parameter values (a fit's corners): the
        lashes' stamp windows take the largest element of all, and the pupil bound (window
        and nearest-depth checks, the crop of the layers' grid) the largest pupil.
        """
        others = list(others)
        for o in others:
            if not isinstance(o, HolographicEye):
                raise ConfigError(f"sized_for takes HolographicEye models, got {type(o).__name__}")
        grid = self.sampling.grid(min(self.wavelengths_nm))
        eye = self.eye.with_stamp_windows(grid, also=[o.eye for o in others])
        pupils = [self._pupil_bound_mm(), *(o._pupil_bound_mm() for o in others)]
        bigger = dataclasses.replace(self, eye=eye, max_pupil_mm=max(pupils))
        need_px = 2 * math.ceil(bigger._need_radius_mm(max(pupils)) / self.sampling.finest_pitch_mm)
        if self.layer_npix < self.npix and self.layer_npix < need_px + 2 * TAPER_PX:
            least = min(self.npix, fft_size(need_px + 2 * TAPER_PX, even=True))
            bigger = dataclasses.replace(bigger, layer_npix=least)
        bigger.check_sampling(max(pupils))
        return bigger

    # ------------------------------------------------------------------ config

    def to_config(self) -> dict[str, Any]:
        """The config of this eye, every choice explicit: ``build_model(m.to_config())``
        rebuilds it (the sampling written as ``output.pixel_scale_deg``, keys as
        ``key_data``)."""
        fr = self.frustum
        frustum: dict[str, Any] = {
            "depth_encoding": fr.depth_encoding,
            "depth_unit_mm": fr.depth_unit_mm,
        }
        if fr.fov_x_deg is not None:
            frustum["fov_x_deg"] = fr.fov_x_deg
        if fr.near_mm is not None:
            frustum["near_m"] = fr.near_mm / 1000.0
        if fr.far_mm is not None:
            frustum["far_m"] = fr.far_mm / 1000.0
        table: dict[str, Any] = {
            "kind": "holographic",
            "accommodation_d": _num(self.accommodation_d),
            "depth_mm": _num(self.depth_mm),
            "mode": self.mode,
            "iterations": self.iterations,
            "phases": self.phases,
            "input_step": self.input_step,
            "depth_layers": self.depth_layers,
            "psf_tiles": self.psf_tiles,
            "memory_budget_mb": self.memory_budget_mb,
            "max_pupil_mm": self.max_pupil_mm,
            "layer_npix": self.layer_npix,
            "layers": {name: name in self.layers for name in LAYERS},
            "geometry": {name: getattr(self, name) for name in _GEOMETRY_KEYS},
            "frustum": frustum,
            "eye": eye_to_config(self.eye),
        }
        if self.tear_film is not None:
            table["tear_film"] = _tear_film_table(self.tear_film)
        if self.spectacles is not None:
            sp = self.spectacles
            table["spectacles"] = {
                "sphere_d": _num(sp.sphere_d),
                "cylinder_d": _num(sp.cylinder_d),
                "axis_deg": _num(sp.axis_deg),
            }
        return {
            "model": table,
            "output": {"npix": self.npix, "pixel_scale_deg": self.pixel_scale_deg},
            "spectrum": {"wavelengths_nm": list(self.wavelengths_nm)},
        }


# Jitted at the public boundary: one compiled program per model structure and input shape
# (validation runs before, on concrete values).


@eqx.filter_jit
def _render(model: HolographicEye, frame, depth, key, iterations: int, time_s) -> Array:
    return model._render_core(frame, depth, key, iterations, time_s)


@eqx.filter_jit
def _speckle_free(model: HolographicEye, frame, depth, time_s, tiles: int) -> Array:
    return model._speckle_free_core(frame, depth, time_s, tiles)


@eqx.filter_jit
def _psf(model: HolographicEye, light_angle_deg, depth_mm, time_s) -> Array:
    return model._psf_core(light_angle_deg, depth_mm, time_s)


# ======================================================================================
# configuration

_GEOMETRY_KEYS = ("lash_distance_mm", "cornea_distance_mm", "spectacle_distance_mm")


def _key_data(key) -> list[int]:
    return [int(v) for v in np.asarray(jax.random.key_data(key)).ravel()]


def _num(x) -> float:
    arr = np.asarray(x)
    value = arr.item() if arr.dtype == np.float64 else float(str(np.float32(arr)))
    return float(value)


def _tear_film_table(film: TearFilm) -> dict[str, Any]:
    out: dict[str, Any] = {
        "pattern": film.pattern,
        "amplitude_um": _num(film.amplitude_um),
        "scale_mm": _num(film.scale_mm),
        "angle_deg": _num(film.angle_deg),
        "n_modes": film.n_modes,
        "refractive_index": film.refractive_index,
        "thickness_um": _num(film.thickness_um),
        "irregularity_growth_per_s": _num(film.irregularity_growth_per_s),
        "thinning_um_per_s": _num(film.thinning_um_per_s),
        "breakup_spots": film.breakup_spots,
        "breakup_growth_mm_per_s": _num(film.breakup_growth_mm_per_s),
        "breakup_edge_mm": _num(film.breakup_edge_mm),
        "breakup_region_mm": _num(film.breakup_region_mm),
        "key_data": _key_data(film.key),
    }
    t_bu = _num(film.breakup_time_s)
    if math.isfinite(t_bu):  # TOML writers differ on inf: leave it out (the default)
        out["breakup_time_s"] = t_bu
    return out
