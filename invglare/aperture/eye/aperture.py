"""The eye's aperture: the pupil function and the obstacle image, rasterised together."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from invglare._core.checks import as_float
from invglare._core.grids import ApertureGrid
from invglare.aperture.eye.inclusions import Gratings, Particles
from invglare.aperture.eye.lashes import Eyelashes
from invglare.aperture.eye.pool import stamp_bound
from invglare.aperture.eye.pupil import Eyelids, Pupil
from invglare.aperture.shapes.primitives import ImageMask, shifted_image_transmission
from invglare.aperture.shapes.stamps import window_half_px
from invglare.errors import ConfigError, PhysicsRangeError


def _stamped(eye) -> list:
    """The eye's stamped components in a fixed order (None where absent)."""
    return [eye.upper_lashes, eye.lower_lashes, *eye.particles, eye.gratings]


def _with_stamped(eye, components: list):
    """`eye` with its stamped components replaced, in the order of :func:`_stamped`."""
    return dataclasses.replace(
        eye,
        upper_lashes=components[0],
        lower_lashes=components[1],
        particles=tuple(components[2:-1]),
        gratings=components[-1],
    )


def _as_particle_tuple(value) -> tuple:
    if value is None:
        return ()
    if isinstance(value, Particles):
        return (value,)
    return tuple(value)


class EyeAperture(eqx.Module):
    """The eye's aperture: pupil function ``P`` and obstacle image ``t_o``.

    **Arguments:**

    - `pupil`: a :class:`Pupil`.
    - `lids`: :class:`Eyelids` or None (no lids).
    - `upper_lashes`, `lower_lashes`: :class:`Eyelashes` (with ``lid`` ``"upper"`` /
      ``"lower"``) or None; lashes need `lids` (they are rooted on the margins).
    - `particles`: a sequence of :class:`Particles` populations (stored as a tuple).
    - `gratings`: :class:`Gratings` or None.
    - `obstacle_image`: an :class:`~invglare.aperture.ImageMask` in the obstacle plane, or
      None: any picture of an obstacle (a photo of lashes, a drawing), Kakimoto et al.'s
      ``t_o``. It multiplies the lids and lashes by ``1 - coverage``: with ``role =
      "block"`` white passes light and black stops it, with ``role = "open"`` the other
      way round; outside the image the plane is clear. It slides over the pupil with the
      light like the lids (position masking), and its placement (`center_mm`,
      `rotation_deg`, `width_mm`) is differentiable.
    - `pupil_image`: an :class:`~invglare.aperture.ImageMask` (``role = "open"``: white
      passes) multiplying the pupil opening, or None: a pupil of any shape (set the
      procedural pupil at least as large as the image).

    Parameters are addressed by path for fitting, e.g.
    ``eqx.tree_at(lambda e: e.upper_lashes.count, eye, 60.5)``.

    **Example:**

    ```python
    eye = night_eye(jax.random.key(0))
    grid = ApertureGrid.from_width(512, eye.extent_mm() * 1.02)
    t = eye.transmission(grid)  # P * t_o
    ```
    """

    pupil: Pupil
    lids: Eyelids | None = None
    upper_lashes: Eyelashes | None = None
    lower_lashes: Eyelashes | None = None
    particles: tuple = eqx.field(converter=_as_particle_tuple, default=())
    gratings: Gratings | None = None
    obstacle_image: ImageMask | None = None
    pupil_image: ImageMask | None = None

    def __check_init__(self):
        def need(name, value, cls, optional=True):
            if (value is None and not optional) or (
                value is not None and not isinstance(value, cls)
            ):
                raise ConfigError(
                    f"eye {name} must be a {cls.__name__}, got {type(value).__name__}"
                )

        need("pupil", self.pupil, Pupil, optional=False)
        need("lids", self.lids, Eyelids)
        need("upper_lashes", self.upper_lashes, Eyelashes)
        need("lower_lashes", self.lower_lashes, Eyelashes)
        need("gratings", self.gratings, Gratings)
        need("obstacle_image", self.obstacle_image, ImageMask)
        need("pupil_image", self.pupil_image, ImageMask)
        for i, p in enumerate(self.particles):
            need(f"particles[{i}]", p, Particles, optional=False)
        for name, lashes, lid in (
            ("upper_lashes", self.upper_lashes, "upper"),
            ("lower_lashes", self.lower_lashes, "lower"),
        ):
            if lashes is None:
                continue
            if lashes.lid != lid:
                raise ConfigError(
                    f"eye {name} must hang from the {lid} lid, got lid={lashes.lid!r}"
                )
            if self.lids is None:
                raise ConfigError(
                    f"eye {name} are rooted on the lid margins: give lids as well "
                    "(wide-open Eyelids() if the lids should not occlude)"
                )

    # -- the two images ------------------------------------------------------------

    def pupil_transmission(self, grid: ApertureGrid) -> Float[Array, "n n"]:
        """``P``: the pupil opening times the particles and gratings inside the eye."""
        return _pupil_image(self._resolve_windows(grid), grid)

    def obstacle_transmission(
        self, grid: ApertureGrid, shift_mm: Float[ArrayLike, " 2"] = (0.0, 0.0)
    ) -> Float[Array, "n n"]:
        """``t_o``: lids times lashes (times the obstacle image), translated by `shift_mm`.

        Translating the obstacle image by ``(d_o / f) * x_f`` relative to the pupil is
        the position-dependent masking of Kakimoto eq. 3 (the light from direction
        ``x_f / f`` sees the lashes shifted); 0 gives the fixed mask of eq. 5.
        Differentiable in `shift_mm` and vmappable over it. Without lids and image it is 1.
        """
        return _obstacle_image(self._resolve_windows(grid), grid, as_float(shift_mm))

    def opening(self, grid: ApertureGrid) -> Float[Array, "n n"]:
        """The pupil's opening: the pupil (times the pupil image), without what lies inside."""
        opening = self.pupil.coverage(grid)
        if self.pupil_image is not None:
            opening = opening * self.pupil_image.coverage(grid)
        return opening

    def transmission(self, grid: ApertureGrid) -> Float[Array, "n n"]:
        """``P * t_o`` with the obstacle unshifted (Kakimoto eq. 5's fixed mask)."""
        return _eye_image(self._resolve_windows(grid), grid)

    def _resolve_windows(self, grid: ApertureGrid) -> EyeAperture:
        """A copy with every stamp window size fixed for `grid` (static shapes for `jit`)."""

        def fix(component):
            if component is None or component.stamp_half_px is not None:
                return component
            return dataclasses.replace(component, stamp_half_px=component.window_half_px(grid))

        return _with_stamped(self, [fix(c) for c in _stamped(self)])

    def extent_mm(self, margin_mm: float = 0.0) -> float:
        """Diameter (mm) of the disk about the axis that holds the pupil, plus `margin_mm` per side.

        ``P`` is 0 outside the pupil, so this is the aperture window needed (concrete
        values only). :meth:`invglare.models.aperture_psf.AperturePSF.build` adds its
        own two-pixel margin.
        """
        return 2.0 * (self.pupil.extent_radius_mm() + float(margin_mm))

    # -- static stamp windows ------------------------------------------------------

    def with_stamp_windows(
        self,
        grid: ApertureGrid | None = None,
        headroom: float = 1.5,
        *,
        also: Sequence[EyeAperture] = (),
    ) -> EyeAperture:
        """A copy whose stamp windows are fixed, for `jit` / `grad` over element sizes.

        Each stamped component (lashes, particles, gratings) gets ``stamp_bound_mm =
        headroom * (largest element half-extent)``; with a `grid` (concrete pitch) also
        ``stamp_half_px``, which is what a `jit` with a traced grid needs. Elements that
        later grow beyond the bound (e.g. during a fit) are cut at their window's edge, so
        leave room with `headroom` (>= 1), or pass in `also` the same eye at the other
        parameter values it will take (e.g. the corners of a fit's bounds): the largest
        half-extent is then taken over this eye and those, and ``headroom=1`` is safe.
        A window only sets which pixels an element is evaluated on, so a tighter one
        changes no value, only the cost (a stamp costs the window's area).
        """
        if not headroom >= 1.0:
            raise PhysicsRangeError(f"stamp window headroom must be >= 1, got {headroom}")
        others = tuple(also)
        for other in others:
            if not isinstance(other, EyeAperture) or len(_stamped(other)) != len(_stamped(self)):
                raise ConfigError(
                    "with_stamp_windows(also=...) takes the same eye at other parameter "
                    f"values, got {type(other).__name__}"
                )

        def bound_of(component) -> float:
            try:
                return float(stamp_bound(component))
            except jax.errors.ConcretizationTypeError as err:
                raise ConfigError(
                    "with_stamp_windows needs concrete parameters: call it outside jit / "
                    "grad / vmap over the eye"
                ) from err

        fixed = []
        for slot, component in enumerate(_stamped(self)):
            if component is None:
                fixed.append(None)
                continue
            largest = max(bound_of(c) for c in (component, *(_stamped(o)[slot] for o in others)))
            bound = headroom * largest
            half = None if grid is None else window_half_px(bound, grid.pitch_mm)
            fixed.append(dataclasses.replace(component, stamp_bound_mm=bound, stamp_half_px=half))
        return _with_stamped(self, fixed)

    # -- configuration -------------------------------------------------------------

    def to_config(self) -> dict[str, Any]:
        """The configuration table of this eye; see :func:`~invglare.aperture.eye.eye_to_config`.

        (The reader is :func:`invglare.config.eye.eye_from_config`.)
        """
        # Imported here: the writer's module needs this class first.
        from invglare.aperture.eye.schema import eye_to_config

        return eye_to_config(self)


# The rasterisation itself is jitted as a whole (after the stamp windows are fixed): one
# compiled program per eye structure, instead of hundreds of separately dispatched operations.


@eqx.filter_jit
def _pupil_image(eye: EyeAperture, grid: ApertureGrid) -> Array:
    opening = eye.opening(grid)
    if not eye.particles and eye.gratings is None:
        return opening
    log_t = jnp.zeros_like(opening)
    for population in eye.particles:
        log_t = log_t + population.log_transmission(grid)
    if eye.gratings is not None:
        log_t = log_t + eye.gratings.log_transmission(grid)
    return opening * jnp.exp(log_t)


@eqx.filter_jit
def _obstacle_image(eye: EyeAperture, grid: ApertureGrid, shift_mm: Array) -> Array:
    dtype = jnp.result_type(grid.pitch_mm, float)
    out = jnp.ones((grid.npix, grid.npix), dtype=dtype)
    if eye.obstacle_image is not None:
        out = out * shifted_image_transmission(eye.obstacle_image, grid, shift_mm)
    if eye.lids is None:
        return out
    out = out * eye.lids.transmission(grid, shift_mm)
    if eye.upper_lashes is None and eye.lower_lashes is None:
        return out
    log_t = jnp.zeros_like(out)
    for lashes in (eye.upper_lashes, eye.lower_lashes):
        if lashes is not None:
            log_t = log_t + lashes.log_transmission(grid, eye.lids, shift_mm)
    return out * jnp.exp(log_t)


@eqx.filter_jit
def _eye_image(eye: EyeAperture, grid: ApertureGrid) -> Array:
    shift = jnp.zeros(2, dtype=jnp.result_type(grid.pitch_mm, float))
    return _pupil_image(eye, grid) * _obstacle_image(eye, grid, shift)
