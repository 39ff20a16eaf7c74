"""The human eye as a parametric, differentiable aperture.

Two images make up the eye's aperture, as in Kakimoto et al. (2004):

* the **pupil function** ``P``: the pupil opening and the structures inside the eye
  that sit (after projection) in the pupil plane: cornea cells, lens-nucleus and
  vitreous particles, lens-fibre gratings (Ritschel et al. 2009, sec. 3);
* the **obstacle image** ``t_o``: the eyelids and eyelashes in front of the eye.

The glare is ``|F[t_o * P]|**2`` (Kakimoto eq. 5, a fixed mask); for the
position-dependent glare of their eq. 3 the obstacle image is translated
relative to the pupil (:meth:`EyeAperture.obstacle_transmission` with `shift_mm`).

**Units and frame.** Lengths in mm in the pupil plane, angles in degrees
counter-clockwise from +x towards +y; the grid's origin (index ``npix // 2``) is
the eye's axis; y points up (the upper lid is at ``y > 0``). See
:class:`~invglare._core.grids.ApertureGrid`.

**Relaxed counts.** Lashes, particles and gratings are drawn as a fixed pool of
`n_max` elements from an explicit `jax.random` key; element `i` is weighted by
``smooth_step(count - i)`` (a cubic step from 0 at ``count = i`` to 1 at
``count = i + 1``). At an integer count exactly that many elements are present;
in between, one element fades in. Element `i`'s random numbers come from
``fold_in(key, i)``, so they do not depend on `n_max`: growing the pool keeps
the existing elements. The draws are *unit* random numbers (uniform or standard
normal) scaled by the parameters, so gradients reach spreads, lengths and sizes.
The derivative with respect to a count is 0 at exact integers (the step is
flat at both ends); start a fit at a non-integer count.

**Stamps.** Particles, grating lines and lash segments are rasterised on small
local windows (:mod:`invglare.aperture.stamps`): an element costs its own size in
pixels squared, not the grid's area (a lash, being long, costs its length times a
window a few widths across). The window size is a static shape: it is computed from
concrete parameters and the grid pitch, or fixed beforehand with
:meth:`EyeAperture.with_stamp_windows` for use inside `jit` / `grad` / `vmap` over
element sizes or a traced grid.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Key

from invglare._core.checks import as_float, as_key, check_range, choose, is_concrete
from invglare._core.grids import ApertureGrid
from invglare.aperture.coverage import curved_edge_coverage
from invglare.aperture.primitives import Ellipse
from invglare.aperture.stamps import (
    disks_log_transmission,
    polyline_log_transmission,
    segments_log_transmission,
    window_half_px,
)
from invglare.dynamics.noise import normal, uniform
from invglare.errors import ConfigError, PhysicsRangeError

#: Where a population of particles lives; see :class:`Particles`.
REGIONS = ("cornea", "lens_nucleus", "vitreous")

#: Which lid a row of lashes hangs from.
LIDS = ("upper", "lower")

#: Standard-normal draws of particle radii are clipped to this many sigmas, so that the
#: largest radius (and with it the stamp window) is bounded.
_RADIUS_CLIP_SIGMA = 3.0


# --------------------------------------------------------------------------------------
# small helpers


def _check_finite(name: str, value, shape: tuple = ()) -> None:
    if not is_concrete(value):
        return
    arr = np.asarray(value, dtype=float)
    if arr.shape != shape or not np.all(np.isfinite(arr)):
        raise PhysicsRangeError(f"{name} must be finite with shape {shape}, got {arr!r}")


def _check_n_max(owner: str, n_max) -> None:
    if not isinstance(n_max, int | np.integer) or isinstance(n_max, bool):
        raise ConfigError(f"{owner} n_max must be an integer (static pool size), got {n_max!r}")
    if n_max < 1:
        raise PhysicsRangeError(f"{owner} n_max must be >= 1, got {n_max}")


def _check_count(owner: str, count, n_max: int) -> None:
    check_range(f"{owner} count", count, 0.0, float(n_max))



def _check_static_int(name: str, value, lo: int) -> None:
    if not isinstance(value, int | np.integer) or isinstance(value, bool) or value < lo:
        raise ConfigError(f"{name} must be an integer >= {lo}, got {value!r}")


def smooth_step(t: Float[ArrayLike, "*shape"]) -> Float[Array, "*shape"]:
    """Cubic step ``3 t**2 - 2 t**3`` on ``[0, 1]``, 0 below and 1 above; C1 everywhere."""
    t = jnp.clip(jnp.asarray(t), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def relaxed_weights(count: Float[ArrayLike, ""], n_max: int) -> Float[Array, " n_max"]:
    """Weights ``smooth_step(count - i)`` of the pool elements ``i = 0 .. n_max - 1``.

    At an integer `count` = k the first k weights are 1 and the rest 0.
    """
    count = as_float(count)
    return smooth_step(count - jnp.arange(n_max, dtype=count.dtype))


def _unit_draws(
    key: Key[Array, ""], n: int, n_uniform: int, n_normal: int, dtype
) -> tuple[Float[Array, "n u"], Float[Array, "n g"]]:
    """Per-element uniform(0, 1) and standard-normal draws, element `i` from ``fold_in(key, i)``.

    Drawing per element (rather than one array of `n` draws) makes element `i`'s
    numbers independent of `n`, so pools of different `n_max` share their elements.
    """

    def one(i):
        k_u, k_n = jax.random.split(jax.random.fold_in(key, i))
        return (
            uniform(k_u, (n_uniform,), dtype),
            normal(k_n, (n_normal,), dtype),
        )

    return jax.vmap(one)(jnp.arange(n))


def _dtype_of(*values) -> Any:
    return jnp.result_type(*values, float)


@eqx.filter_jit
def _stamp_bound(component) -> Array:
    # jitted: evaluated eagerly, the few dozen small operations would each be compiled.
    return component.stamp_bound()


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


def _stamp_window(owner: str, grid: ApertureGrid, component) -> int:
    """The window half-size (px) of a stamped component (see the module docstring)."""
    if component.stamp_half_px is not None:
        return int(component.stamp_half_px)
    bound = component.stamp_bound_mm
    if bound is None:
        bound = _stamp_bound(component)
    try:
        return window_half_px(bound, grid.pitch_mm)
    except ConfigError as err:
        raise ConfigError(f"{owner}: {err}") from err


# --------------------------------------------------------------------------------------
# pupil and lids


class Pupil(eqx.Module):
    """The pupil opening: an ellipse (a circle by default).

    **Arguments:**

    - `diameter_mm`: pupil diameter (major axis), > 0. About 2-3 mm in daylight and
      7-8 mm at night.
    - `ellipticity`: in ``[0, 1)``; the minor axis is ``diameter * (1 - ellipticity)``.
    - `rotation_deg`: direction of the major axis, from +x.
    - `decentration_mm`: (x, y) offset of the pupil centre from the eye's axis.
    """

    diameter_mm: Float[Array, ""] = eqx.field(converter=as_float)
    ellipticity: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)
    rotation_deg: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)
    decentration_mm: Float[Array, " 2"] = eqx.field(converter=as_float, default=(0.0, 0.0))

    def __check_init__(self):
        check_range("pupil diameter_mm", self.diameter_mm, 0.0, lo_open=True, unit="mm")
        check_range("pupil ellipticity", self.ellipticity, 0.0, 1.0)
        if is_concrete(self.ellipticity) and float(self.ellipticity) >= 1.0:
            raise PhysicsRangeError(f"pupil ellipticity must be < 1, got {float(self.ellipticity)}")
        _check_finite("pupil rotation_deg", self.rotation_deg)
        _check_finite("pupil decentration_mm", self.decentration_mm, (2,))

    def shape(self) -> Ellipse:
        """The pupil as an open :class:`~invglare.aperture.Ellipse`."""
        return Ellipse(self.diameter_mm, self.ellipticity, self.rotation_deg, self.decentration_mm)

    def coverage(self, grid: ApertureGrid) -> Float[Array, "n n"]:
        """Fraction of each pixel inside the pupil."""
        return self.shape().coverage(grid)

    def extent_radius_mm(self) -> float:
        """Distance (mm) from the axis to the farthest point of the pupil (concrete)."""
        return float(np.hypot(*np.asarray(self.decentration_mm))) + 0.5 * float(self.diameter_mm)


class Eyelids(eqx.Module):
    """Upper and lower eyelids: occluders beyond two gently curved margins.

    Each lid margin is the parabola ``y' = opening - curvature * x'**2 / 2`` in the
    lid's own frame (rotated by its tilt about the eye's axis; ``y'`` points away
    from the axis, up for the upper lid and down for the lower one), and the lid
    covers everything beyond it. A blink is both openings at 0 (with equal tilts, so
    that the margins meet; unequal tilts leave a wedge open on one side); squinting is
    any smaller opening: only parameter changes.

    **Arguments:**

    - `upper_opening_mm`, `lower_opening_mm`: distance (mm, >= 0) from the eye's axis
      to each lid margin (defaults 4.5 and 4.0: a relaxed, wide-open eye).
    - `upper_tilt_deg`, `lower_tilt_deg`: counter-clockwise rotation of each margin.
    - `curvature_per_mm`: curvature (1/mm, >= 0) of both margins at their apex; the
      default 0.04 closes a 4.5 mm opening over 15 mm, about a real palpebral fissure.

    The two lids' coverages are added (they do not overlap within a pixel while the
    eye is open) and clipped to 1, so two margins meeting at the axis close it
    completely.
    """

    upper_opening_mm: Float[Array, ""] = eqx.field(converter=as_float, default=4.5)
    lower_opening_mm: Float[Array, ""] = eqx.field(converter=as_float, default=4.0)
    upper_tilt_deg: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)
    lower_tilt_deg: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)
    curvature_per_mm: Float[Array, ""] = eqx.field(converter=as_float, default=0.04)

    def __check_init__(self):
        check_range("lids upper_opening_mm", self.upper_opening_mm, 0.0, unit="mm")
        check_range("lids lower_opening_mm", self.lower_opening_mm, 0.0, unit="mm")
        _check_finite("lids upper_tilt_deg", self.upper_tilt_deg)
        _check_finite("lids lower_tilt_deg", self.lower_tilt_deg)
        check_range("lids curvature_per_mm", self.curvature_per_mm, 0.0, unit="1/mm")

    def _lid(self, lid: str) -> tuple[Array, Array, float]:
        """(opening mm, tilt rad, sign of y' in the lid frame)."""
        choose("lid", lid, LIDS)
        if lid == "upper":
            return self.upper_opening_mm, jnp.deg2rad(self.upper_tilt_deg), 1.0
        return self.lower_opening_mm, jnp.deg2rad(self.lower_tilt_deg), -1.0

    def margin(
        self, lid: str, x_mm: Float[ArrayLike, " m"], shift_mm: ArrayLike = (0.0, 0.0)
    ) -> tuple[Float[Array, "m 2"], Float[Array, "m 2"]]:
        """Points on a lid margin and the unit normals there pointing into the opening.

        `x_mm` is the position along the margin in the lid's frame (0 at its apex);
        `shift_mm` translates the lids (the obstacle shift).
        """
        opening, tilt, sign = self._lid(lid)
        kappa = self.curvature_per_mm
        x = jnp.asarray(x_mm)
        y_lid = sign * (opening - 0.5 * kappa * x * x)
        g = jnp.sqrt(1.0 + (kappa * x) ** 2)
        nx_lid, ny_lid = -kappa * x / g, -sign / g
        c, s = jnp.cos(tilt), jnp.sin(tilt)
        shift = as_float(shift_mm)
        points = jnp.stack([c * x - s * y_lid + shift[0], s * x + c * y_lid + shift[1]], -1)
        normals = jnp.stack([c * nx_lid - s * ny_lid, s * nx_lid + c * ny_lid], -1)
        return points, normals

    def lid_coverage(
        self, grid: ApertureGrid, lid: str, shift_mm: ArrayLike = (0.0, 0.0)
    ) -> Float[Array, "n n"]:
        """Fraction of each pixel covered by one lid (``"upper"`` or ``"lower"``)."""
        opening, tilt, sign = self._lid(lid)
        kappa = self.curvature_per_mm
        shift = as_float(shift_mm)
        y, x = grid.mesh_mm()
        px, py = x - shift[0], y - shift[1]
        c, s = jnp.cos(tilt), jnp.sin(tilt)
        x_lid = c * px + s * py
        y_away = sign * (-s * px + c * py)  # distance from the axis towards the lid
        # f > 0 inside the lid; f / |grad f| is the signed distance to first order, exact
        # on the margin.
        f = y_away - opening + 0.5 * kappa * x_lid * x_lid
        g = jnp.sqrt(1.0 + (kappa * x_lid) ** 2)
        sd = -f / g
        # Outward normal of the lid region (towards the opening), back in grid axes.
        nx_lid, ny_lid = -kappa * x_lid / g, -sign / g
        nx = c * nx_lid - s * ny_lid
        ny = s * nx_lid + c * ny_lid
        # The lid region is concave along its margin: negative curvature.
        curvature = -kappa / g**3
        pitch = grid.pitch_mm
        return curved_edge_coverage(sd * (1.0 / pitch), nx, ny, curvature * pitch)

    def coverage(self, grid: ApertureGrid, shift_mm: ArrayLike = (0.0, 0.0)) -> Float[Array, "n n"]:
        """Fraction of each pixel covered by either lid, ``min(1, c_upper + c_lower)``."""
        both = self.lid_coverage(grid, "upper", shift_mm) + self.lid_coverage(
            grid, "lower", shift_mm
        )
        return jnp.clip(both, 0.0, 1.0)

    def transmission(
        self, grid: ApertureGrid, shift_mm: ArrayLike = (0.0, 0.0)
    ) -> Float[Array, "n n"]:
        """``1 - coverage``: what the lids let through."""
        return 1.0 - self.coverage(grid, shift_mm)


# --------------------------------------------------------------------------------------
# eyelashes


class Eyelashes(eqx.Module):
    """A row of eyelashes rooted along one lid margin.

    **Arguments:**

    - `count`: number of lashes (float, relaxed; ``0 <= count <= n_max``).
    - `n_max`: size of the pool (static).
    - `key`: `jax.random` key of the per-lash variations (a typed key, raw ``uint32``
      key data or an int seed; stored as a typed key).
    - `lid`: ``"upper"`` or ``"lower"`` (static).
    - `mean_angle_deg`: mean direction of the lashes relative to the margin's normal
      into the opening (0: lashes point straight across the opening, towards the
      axis); counter-clockwise positive.
    - `angular_spread_deg`: standard deviation of the per-lash direction.
    - `spacing_jitter`: root positions are ``count`` even slots over `root_span_mm`,
      each moved by ``spacing_jitter * spacing * (u - 1/2)``, ``u ~ U(0, 1)``.
    - `thickness_mm`, `length_mm`: mean width and length of a lash (pupil-plane
      silhouette), each varied per lash by ``1 + spread * U(-1, 1)`` with
      `thickness_spread`, `length_spread` in ``[0, 1)``.
    - `curvature_per_mm`: signed curvature of each lash (1/mm), positive bending
      counter-clockwise; the lash is the parabola
      ``root + s d + curvature * s**2 / 2 * d_perp`` for ``0 <= s <= length``.
    - `root_span_mm`: length of the stretch of margin (centred on its apex) holding
      the roots.
    - `segments`: straight segments per lash (static, default 8); each chord departs
      from the parabola by at most ``curvature * length**2 / (8 * segments**2)`` (under
      a micrometre for the defaults with a curvature of 0.05 /mm).
    - `stamp_bound_mm`, `stamp_half_px`: static stamp-window overrides (see
      :meth:`EyeAperture.with_stamp_windows`); leave them None for automatic windows.

    Lash `i` is present with weight ``smooth_step(count - i)``; the slots are
    ``span / max(count, 1)`` apart, so the lashes spread evenly at any count and
    move smoothly as it changes. Lashes are fully opaque. Each lash is a polyline
    stamped segment by segment (see
    :func:`invglare.aperture.stamps.polyline_log_transmission`): the cost is
    proportional to the lash's length in pixels times the window, not to the grid area.
    """

    count: Float[Array, ""] = eqx.field(converter=as_float)
    n_max: int = eqx.field(static=True)
    key: Key[Array, ""] = eqx.field(converter=as_key)
    lid: str = eqx.field(static=True, default="upper")
    mean_angle_deg: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)
    angular_spread_deg: Float[Array, ""] = eqx.field(converter=as_float, default=10.0)
    spacing_jitter: Float[Array, ""] = eqx.field(converter=as_float, default=0.5)
    thickness_mm: Float[Array, ""] = eqx.field(converter=as_float, default=0.08)
    length_mm: Float[Array, ""] = eqx.field(converter=as_float, default=3.0)
    curvature_per_mm: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)
    root_span_mm: Float[Array, ""] = eqx.field(converter=as_float, default=8.0)
    length_spread: Float[Array, ""] = eqx.field(converter=as_float, default=0.2)
    thickness_spread: Float[Array, ""] = eqx.field(converter=as_float, default=0.2)
    segments: int = eqx.field(static=True, default=8)
    stamp_bound_mm: float | None = eqx.field(static=True, default=None)
    stamp_half_px: int | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        owner = f"{self.lid} lashes"
        choose("lashes lid", self.lid, LIDS)
        _check_n_max(owner, self.n_max)
        _check_count(owner, self.count, self.n_max)
        _check_static_int(f"{owner} segments", self.segments, 1)
        _check_finite(f"{owner} mean_angle_deg", self.mean_angle_deg)
        check_range(f"{owner} angular_spread_deg", self.angular_spread_deg, 0.0, unit="deg")
        check_range(f"{owner} spacing_jitter", self.spacing_jitter, 0.0)
        check_range(f"{owner} thickness_mm", self.thickness_mm, 0.0, lo_open=True, unit="mm")
        check_range(f"{owner} length_mm", self.length_mm, 0.0, lo_open=True, unit="mm")
        _check_finite(f"{owner} curvature_per_mm", self.curvature_per_mm)
        check_range(f"{owner} root_span_mm", self.root_span_mm, 0.0, lo_open=True, unit="mm")
        check_range(f"{owner} length_spread", self.length_spread, 0.0, 0.999)
        check_range(f"{owner} thickness_spread", self.thickness_spread, 0.0, 0.999)

    def _draws(self):
        dtype = _dtype_of(self.length_mm, self.thickness_mm, self.mean_angle_deg)
        u, z = _unit_draws(self.key, self.n_max, 3, 1, dtype)
        length = self.length_mm * (1.0 + self.length_spread * (2.0 * u[:, 0] - 1.0))
        thickness = self.thickness_mm * (1.0 + self.thickness_spread * (2.0 * u[:, 1] - 1.0))
        return u[:, 2], z[:, 0], length, thickness

    def weights(self) -> Float[Array, " n_max"]:
        """Relaxed-count weight of each lash of the pool."""
        return relaxed_weights(self.count, self.n_max)

    def polylines(
        self, lids: Eyelids, shift_mm: ArrayLike = (0.0, 0.0)
    ) -> tuple[Float[Array, "n_max s+1 2"], Float[Array, " n_max"], Float[Array, " n_max"]]:
        """Vertices (mm), thickness (mm) and weight of every lash of the pool."""
        jitter_u, angle_z, length, thickness = self._draws()
        dtype = length.dtype
        i = jnp.arange(self.n_max, dtype=dtype)
        spacing = self.root_span_mm / jnp.maximum(self.count, 1.0)
        x_root = (i + 0.5) * spacing - 0.5 * self.root_span_mm
        x_root = x_root + self.spacing_jitter * spacing * (jitter_u - 0.5)
        roots, normals = lids.margin(self.lid, x_root, shift_mm)
        angle = jnp.arctan2(normals[:, 1], normals[:, 0]) + jnp.deg2rad(
            self.mean_angle_deg + self.angular_spread_deg * angle_z
        )
        d = jnp.stack([jnp.cos(angle), jnp.sin(angle)], -1)
        d_perp = jnp.stack([-d[:, 1], d[:, 0]], -1)
        s = jnp.linspace(0.0, 1.0, self.segments + 1, dtype=dtype)[None, :] * length[:, None]
        bend = 0.5 * self.curvature_per_mm * s * s
        points = (
            roots[:, None, :] + s[..., None] * d[:, None, :] + bend[..., None] * d_perp[:, None]
        )
        return points, thickness, self.weights()

    def stamp_bound(self) -> Float[Array, ""]:
        """Largest half-extent (mm) of the pixels one lash segment claims.

        Half the segment's arc, plus its half-width, which a mitred joint stretches by
        ``tan(bend / 2)`` on the outside of a bend (`bend`, the turn between segments, is
        at most the curvature times a segment's arc). It does not depend on the lids, so
        a gradient through the lid opening needs no fixed window.
        """
        _, _, length, thickness = self._draws()
        arc = length * jnp.sqrt(1.0 + (self.curvature_per_mm * length) ** 2) / self.segments
        bend = jnp.minimum(jnp.abs(self.curvature_per_mm) * arc, 0.5 * math.pi)
        return jnp.max(0.5 * arc + 0.5 * thickness * (1.0 + jnp.tan(0.5 * bend)))

    def window_half_px(self, grid: ApertureGrid) -> int:
        """Static stamp-window half-size (px) on `grid`."""
        return _stamp_window(f"{self.lid} lashes", grid, self)

    def log_transmission(
        self, grid: ApertureGrid, lids: Eyelids, shift_mm: ArrayLike = (0.0, 0.0)
    ) -> Float[Array, "n n"]:
        """``log`` of the lashes' transmission on `grid` (<= 0)."""
        return _lashes_log(self, grid, lids, as_float(shift_mm), self.window_half_px(grid))


# --------------------------------------------------------------------------------------
# particles and gratings


class Particles(eqx.Module):
    """A population of small opaque particles, projected onto the pupil plane.

    **Arguments:**

    - `count`: number of particles (float, relaxed; ``0 <= count <= n_max``).
    - `n_max`: size of the pool (static).
    - `key`: `jax.random` key of the positions and radii (typed key, raw key data or
      an int seed).
    - `region`: ``"cornea"``, ``"lens_nucleus"`` or ``"vitreous"`` (static).
    - `radius_mean_mm`: mean particle radius (mm, > 0).
    - `radius_spread`: sigma of the log-radius (>= 0): radius
      ``mean * exp(spread * z - spread**2 / 2)``, ``z ~ N(0, 1)`` clipped to +-3,
      a log-normal whose mean is `radius_mean_mm` (before clipping).
    - `region_radius_mm`: size of the region (mm, > 0).
    - `offsets_mm`: optional ``(n_max, 2)`` displacement (mm) added to every drawn
      centre; None (default) leaves the particles where they were drawn. It is how a
      moving eye (:mod:`invglare.models.temporal`) carries lens and vitreous particles
      without changing the draws; not part of the configuration.
    - `stamp_bound_mm`, `stamp_half_px`: static stamp-window overrides.

    **Positions.** Cornea cells lie in a thin layer: uniform over a disk of radius
    `region_radius_mm`. Lens-nucleus and vitreous particles fill a volume: uniform in
    a ball of that radius, projected orthographically (along the optical axis) onto
    the pupil plane, which concentrates them towards the axis (projected density
    ``~ sqrt(R**2 - r**2)``). Following Ritschel et al. (sec. 4) everything is drawn in
    one plane; the particles' different distances to the retina are neglected.
    Particles are centred on the eye's axis and do not move with the pupil's
    decentration or the obstacle shift.
    """

    count: Float[Array, ""] = eqx.field(converter=as_float)
    n_max: int = eqx.field(static=True)
    key: Key[Array, ""] = eqx.field(converter=as_key)
    region: str = eqx.field(static=True, default="lens_nucleus")
    radius_mean_mm: Float[Array, ""] = eqx.field(converter=as_float, default=0.01)
    radius_spread: Float[Array, ""] = eqx.field(converter=as_float, default=0.3)
    region_radius_mm: Float[Array, ""] = eqx.field(converter=as_float, default=2.5)
    offsets_mm: Float[Array, "n_max 2"] | None = None
    stamp_bound_mm: float | None = eqx.field(static=True, default=None)
    stamp_half_px: int | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        choose("particles region", self.region, REGIONS)
        owner = f"{self.region} particles"
        _check_n_max(owner, self.n_max)
        if self.offsets_mm is not None:
            _check_finite(f"{owner} offsets_mm", self.offsets_mm, (self.n_max, 2))
        _check_count(owner, self.count, self.n_max)
        check_range(f"{owner} radius_mean_mm", self.radius_mean_mm, 0.0, lo_open=True, unit="mm")
        check_range(f"{owner} radius_spread", self.radius_spread, 0.0)
        check_range(
            f"{owner} region_radius_mm", self.region_radius_mm, 0.0, lo_open=True, unit="mm"
        )

    def _draws(self):
        dtype = _dtype_of(self.radius_mean_mm, self.region_radius_mm)
        return _unit_draws(self.key, self.n_max, 2, 4, dtype)

    def centers_mm(self) -> Float[Array, "n_max 2"]:
        """Projected particle centres (x, y) in mm, moved by `offsets_mm` when given."""
        centers = self.drawn_centers_mm()
        return centers if self.offsets_mm is None else centers + self.offsets_mm

    def drawn_centers_mm(self) -> Float[Array, "n_max 2"]:
        """Projected centres (x, y) in mm as drawn, without `offsets_mm`."""
        u, z = self._draws()
        big_r = self.region_radius_mm
        if self.region == "cornea":
            r = big_r * jnp.sqrt(u[:, 0])
            phi = 2.0 * math.pi * u[:, 1]
            return jnp.stack([r * jnp.cos(phi), r * jnp.sin(phi)], -1)
        # Uniform in the ball: an isotropic direction (normalised normal vector) times a
        # radius with density ~ r**2; only (x, y) survives the projection.
        direction = z[:, :3] / jnp.linalg.norm(z[:, :3], axis=-1, keepdims=True)
        r = big_r * jnp.cbrt(u[:, 0])
        return r[:, None] * direction[:, :2]

    def radii_mm(self) -> Float[Array, " n_max"]:
        """Particle radii (mm)."""
        _, z = self._draws()
        zc = jnp.clip(z[:, 3], -_RADIUS_CLIP_SIGMA, _RADIUS_CLIP_SIGMA)
        s = self.radius_spread
        return self.radius_mean_mm * jnp.exp(s * zc - 0.5 * s * s)

    def weights(self) -> Float[Array, " n_max"]:
        return relaxed_weights(self.count, self.n_max)

    def stamp_bound(self) -> Float[Array, ""]:
        """Largest particle radius (mm)."""
        return jnp.max(self.radii_mm())

    def window_half_px(self, grid: ApertureGrid) -> int:
        return _stamp_window(f"{self.region} particles", grid, self)

    def log_transmission(self, grid: ApertureGrid) -> Float[Array, "n n"]:
        """``log`` of the particles' transmission on `grid`."""
        return _particles_log(self, grid, self.window_half_px(grid))


class Gratings(eqx.Module):
    """Lens-fibre gratings in the lens cortex: small patches of parallel radial lines.

    Lens fibres run from the lens's poles to its equator, so seen along the axis
    they are radial; their regular spacing makes the cortex a diffraction grating
    (the lenticular halo, Ritschel et al. sec. 3.3). Each grating is a patch of
    `lines_per_grating` parallel line segments pointing radially at the patch
    centre, side by side at `spacing_mm`.

    **Arguments:**

    - `count`: number of gratings (relaxed; ``0 <= count <= n_max``).
    - `n_max`: pool size (static).
    - `key`: `jax.random` key of the patch positions.
    - `spacing_mm`: centre-to-centre distance of the lines in a patch (> 0).
    - `line_thickness_mm`: width of a line (> 0).
    - `line_length_mm`: length of a line (> 0).
    - `inner_radius_mm`, `outer_radius_mm`: the annulus of the lens cortex holding
      the patch centres (``0 <= inner < outer``); centres are uniform in its area.
    - `lines_per_grating`: lines per patch (static, >= 1).
    - `stamp_bound_mm`, `stamp_half_px`: static stamp-window overrides.

    Lines are opaque capsules, stamped one by one.
    """

    count: Float[Array, ""] = eqx.field(converter=as_float)
    n_max: int = eqx.field(static=True)
    key: Key[Array, ""] = eqx.field(converter=as_key)
    spacing_mm: Float[Array, ""] = eqx.field(converter=as_float, default=0.04)
    line_thickness_mm: Float[Array, ""] = eqx.field(converter=as_float, default=0.012)
    line_length_mm: Float[Array, ""] = eqx.field(converter=as_float, default=0.3)
    inner_radius_mm: Float[Array, ""] = eqx.field(converter=as_float, default=2.0)
    outer_radius_mm: Float[Array, ""] = eqx.field(converter=as_float, default=3.5)
    lines_per_grating: int = eqx.field(static=True, default=5)
    stamp_bound_mm: float | None = eqx.field(static=True, default=None)
    stamp_half_px: int | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        _check_n_max("gratings", self.n_max)
        _check_count("gratings", self.count, self.n_max)
        _check_static_int("gratings lines_per_grating", self.lines_per_grating, 1)
        check_range("gratings spacing_mm", self.spacing_mm, 0.0, lo_open=True, unit="mm")
        check_range(
            "gratings line_thickness_mm", self.line_thickness_mm, 0.0, lo_open=True, unit="mm"
        )
        check_range("gratings line_length_mm", self.line_length_mm, 0.0, lo_open=True, unit="mm")
        check_range("gratings inner_radius_mm", self.inner_radius_mm, 0.0, unit="mm")
        check_range("gratings outer_radius_mm", self.outer_radius_mm, 0.0, lo_open=True, unit="mm")
        if is_concrete(self.inner_radius_mm) and is_concrete(self.outer_radius_mm):
            inner, outer = float(self.inner_radius_mm), float(self.outer_radius_mm)
            if inner >= outer:
                raise PhysicsRangeError(
                    f"gratings inner_radius_mm ({inner:g} mm) must be smaller than "
                    f"outer_radius_mm ({outer:g} mm)"
                )

    def lines(
        self,
    ) -> tuple[Float[Array, "m 2"], Float[Array, "m 2"], Float[Array, " m"]]:
        """Start and end points (mm) and weight of every line, ``m = n_max * lines_per_grating``."""
        dtype = _dtype_of(self.spacing_mm, self.inner_radius_mm)
        u, _ = _unit_draws(self.key, self.n_max, 2, 0, dtype)
        r_in, r_out = self.inner_radius_mm, self.outer_radius_mm
        rho = jnp.sqrt(r_in * r_in + u[:, 0] * (r_out * r_out - r_in * r_in))
        phi = 2.0 * math.pi * u[:, 1]
        radial = jnp.stack([jnp.cos(phi), jnp.sin(phi)], -1)
        tangent = jnp.stack([-radial[:, 1], radial[:, 0]], -1)
        centre = rho[:, None] * radial
        lines_n = self.lines_per_grating
        offsets = (jnp.arange(lines_n, dtype=dtype) - 0.5 * (lines_n - 1)) * self.spacing_mm
        mids = centre[:, None, :] + offsets[None, :, None] * tangent[:, None, :]
        half = 0.5 * self.line_length_mm * radial[:, None, :]
        starts = (mids - half).reshape(-1, 2)
        ends = (mids + half).reshape(-1, 2)
        weights = jnp.repeat(relaxed_weights(self.count, self.n_max), lines_n)
        return starts, ends, weights

    def stamp_bound(self) -> Float[Array, ""]:
        """Half-extent (mm) of one line: half its length plus half its width."""
        return 0.5 * (self.line_length_mm + self.line_thickness_mm)

    def window_half_px(self, grid: ApertureGrid) -> int:
        return _stamp_window("gratings", grid, self)

    def log_transmission(self, grid: ApertureGrid) -> Float[Array, "n n"]:
        """``log`` of the gratings' transmission on `grid`."""
        return _gratings_log(self, grid, self.window_half_px(grid))


# Jitted rasterisers of the stamped components (`half_px`, a Python int, is static): evaluated
# eagerly, their few dozen small operations would each be compiled and dispatched.


@eqx.filter_jit
def _lashes_log(
    lashes: Eyelashes, grid: ApertureGrid, lids: Eyelids, shift_mm: Array, half_px: int
) -> Array:
    points, thickness, weights = lashes.polylines(lids, shift_mm)
    return polyline_log_transmission(grid, points, thickness, weights, half_px)


@eqx.filter_jit
def _particles_log(particles: Particles, grid: ApertureGrid, half_px: int) -> Array:
    return disks_log_transmission(
        grid, particles.centers_mm(), particles.radii_mm(), particles.weights(), half_px
    )


@eqx.filter_jit
def _gratings_log(gratings: Gratings, grid: ApertureGrid, half_px: int) -> Array:
    starts, ends, weights = gratings.lines()
    thickness = jnp.broadcast_to(gratings.line_thickness_mm, weights.shape)
    return segments_log_transmission(grid, starts, ends, thickness, weights, half_px)


# --------------------------------------------------------------------------------------
# the whole eye


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
        """``t_o``: lids times lashes, translated by `shift_mm` = (x, y) mm.

        Translating the obstacle image by ``(d_o / f) * x_f`` relative to the pupil is
        the position-dependent masking of Kakimoto eq. 3 (the light from direction
        ``x_f / f`` sees the lashes shifted); 0 gives the fixed mask of eq. 5.
        Differentiable in `shift_mm` and vmappable over it. Without lids it is 1.
        """
        return _obstacle_image(self._resolve_windows(grid), grid, as_float(shift_mm))

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
                return float(_stamp_bound(component))
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

    @classmethod
    def from_config(cls, table: dict[str, Any], where: str = "eye") -> EyeAperture:
        """Build an eye from a configuration table; see :func:`eye_from_config`."""
        return eye_from_config(table, where)

    def to_config(self) -> dict[str, Any]:
        """The configuration table of this eye; see :func:`eye_to_config`."""
        return eye_to_config(self)


# The rasterisation itself is jitted as a whole (after the stamp windows are fixed): one
# compiled program per eye structure, instead of hundreds of separately dispatched operations.


@eqx.filter_jit
def _pupil_image(eye: EyeAperture, grid: ApertureGrid) -> Array:
    opening = eye.pupil.coverage(grid)
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
    if eye.lids is None:
        dtype = jnp.result_type(grid.pitch_mm, float)
        return jnp.ones((grid.npix, grid.npix), dtype=dtype)
    out = eye.lids.transmission(grid, shift_mm)
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


# --------------------------------------------------------------------------------------
# configuration tables

# Value kinds: "number", "int", "point" ([x, y]), "str", "key" (list of uint32 key data).
_PUPIL_KEYS = {
    "diameter_mm": "number",
    "ellipticity": "number",
    "rotation_deg": "number",
    "decentration_mm": "point",
}
_LIDS_KEYS = {
    "upper_opening_mm": "number",
    "lower_opening_mm": "number",
    "upper_tilt_deg": "number",
    "lower_tilt_deg": "number",
    "curvature_per_mm": "number",
}
_LASH_KEYS = {
    "count": "number",
    "n_max": "int",
    "mean_angle_deg": "number",
    "angular_spread_deg": "number",
    "spacing_jitter": "number",
    "thickness_mm": "number",
    "length_mm": "number",
    "curvature_per_mm": "number",
    "root_span_mm": "number",
    "length_spread": "number",
    "thickness_spread": "number",
    "segments": "int",
    "key_data": "key",
}
_PARTICLE_KEYS = {
    "region": "str",
    "count": "number",
    "n_max": "int",
    "radius_mean_mm": "number",
    "radius_spread": "number",
    "region_radius_mm": "number",
    "key_data": "key",
}
_GRATING_KEYS = {
    "count": "number",
    "n_max": "int",
    "spacing_mm": "number",
    "line_thickness_mm": "number",
    "line_length_mm": "number",
    "inner_radius_mm": "number",
    "outer_radius_mm": "number",
    "lines_per_grating": "int",
    "key_data": "key",
}
#: Keys of an eye table (sub-tables, a list of particle tables, and the seed).
EYE_KEYS = ("pupil", "lids", "lashes_upper", "lashes_lower", "particles", "gratings", "seed")

# fold_in tags deriving each component's key from the eye's seed.
_SEED_TAGS = {"lashes_upper": 1, "lashes_lower": 2, "gratings": 3, "particles": 100}


def _is_number(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


def _is_int(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _convert(kind: str, value: Any, name: str) -> Any:
    if kind == "number" and _is_number(value):
        return float(value)
    if kind == "int" and _is_int(value):
        return int(value)
    if kind == "str" and isinstance(value, str):
        return value
    if kind == "point" and isinstance(value, list | tuple) and len(value) == 2:
        if all(_is_number(v) for v in value):
            return (float(value[0]), float(value[1]))
    if kind == "key" and isinstance(value, list | tuple) and value:
        if all(_is_int(v) and 0 <= v < 2**32 for v in value):
            return jax.random.wrap_key_data(np.asarray(value, dtype=np.uint32))
    expected = {
        "number": "a number",
        "int": "an integer",
        "str": "a string",
        "point": "a pair of numbers [x, y]",
        "key": "a list of uint32 integers (jax.random.key_data)",
    }[kind]
    raise ConfigError(f"{name} must be {expected}, got {value!r}")


def _read_table(
    table: Any, keys: dict[str, str], where: str, required: Sequence[str] = ()
) -> dict[str, Any]:
    """Check a sub-table's keys and value types; return the converted values."""
    if not isinstance(table, dict):
        raise ConfigError(f"{where} must be a table, got {table!r}")
    for key in table:
        if key not in keys:
            raise ConfigError(f"{where}: unknown key {key!r}; valid keys: {', '.join(keys)}")
    missing = [k for k in required if k not in table]
    if missing:
        raise ConfigError(
            f"{where}: missing {', '.join(repr(k) for k in missing)} "
            f"(required keys: {', '.join(required)})"
        )
    return {k: _convert(keys[k], v, f"{where}.{k}") for k, v in table.items()}


def _default_n_max(args: dict[str, Any]) -> None:
    if "n_max" not in args:
        args["n_max"] = max(1, math.ceil(args["count"]))


def _build(where: str, cls, args: dict[str, Any]):
    try:
        return cls(**args)
    except (PhysicsRangeError, ConfigError) as err:
        raise type(err)(f"{where}: {err}") from err


def eye_from_config(table: dict[str, Any], where: str = "eye") -> EyeAperture:
    """Build an :class:`EyeAperture` from a TOML-like table.

    **Arguments:**

    - `table`: a dict with the sub-tables below; only `pupil` is required.
    - `where`: where the table sits in the configuration (e.g. ``"model.eye"``), for
      error messages.

    ```toml
    [eye]
    seed = 7                     # int; derives every component's key (default 0)
    [eye.pupil]                  # diameter_mm (required), ellipticity, rotation_deg,
    diameter_mm = 6.0            #   decentration_mm = [x, y]
    [eye.lids]                   # upper/lower_opening_mm, upper/lower_tilt_deg,
    upper_opening_mm = 4.0       #   curvature_per_mm
    [eye.lashes_upper]           # count (required), n_max, mean_angle_deg,
    count = 60                   #   angular_spread_deg, spacing_jitter, thickness_mm,
                                 #   length_mm, curvature_per_mm, root_span_mm,
                                 #   length_spread, thickness_spread, segments, key_data
    [eye.lashes_lower]           # as lashes_upper
    [[eye.particles]]            # region and count (required), n_max, radius_mean_mm,
    region = "lens_nucleus"      #   radius_spread, region_radius_mm, key_data
    count = 750
    [eye.gratings]               # count (required), n_max, spacing_mm,
    count = 200                  #   line_thickness_mm, line_length_mm, inner_radius_mm,
                                 #   outer_radius_mm, lines_per_grating, key_data
    ```

    `n_max` defaults to the count rounded up. A component's key is
    ``fold_in(key(seed), tag)`` unless it gives `key_data` (what
    :func:`eye_to_config` writes, so that a written eye is reproduced exactly).

    **Raises:** `ConfigError` naming the key for an unknown key (listing the valid
    ones), a missing key or a value of the wrong type; `PhysicsRangeError` for
    values out of range, prefixed with where they are.
    """
    if not isinstance(table, dict):
        raise ConfigError(f"{where} must be a table, got {table!r}")
    for key in table:
        if key not in EYE_KEYS:
            raise ConfigError(f"{where}: unknown key {key!r}; valid keys: {', '.join(EYE_KEYS)}")
    if "pupil" not in table:
        raise ConfigError(f"{where}: missing 'pupil' (a table with at least diameter_mm)")
    seed = table.get("seed", 0)
    if not _is_int(seed):
        raise ConfigError(f"{where}.seed must be an integer, got {seed!r}")
    root = jax.random.key(seed)

    def key_for(args: dict[str, Any], tag: int) -> None:
        if "key_data" in args:
            args["key"] = args.pop("key_data")
        else:
            args["key"] = jax.random.fold_in(root, tag)

    name = f"{where}.pupil"
    pupil = _build(name, Pupil, _read_table(table["pupil"], _PUPIL_KEYS, name, ("diameter_mm",)))
    lids = None
    if "lids" in table:
        name = f"{where}.lids"
        lids = _build(name, Eyelids, _read_table(table["lids"], _LIDS_KEYS, name))
    lashes = {}
    for section, lid in (("lashes_upper", "upper"), ("lashes_lower", "lower")):
        if section not in table:
            lashes[lid] = None
            continue
        name = f"{where}.{section}"
        args = _read_table(table[section], _LASH_KEYS, name, ("count",))
        _default_n_max(args)
        key_for(args, _SEED_TAGS[section])
        lashes[lid] = _build(name, Eyelashes, {**args, "lid": lid})
    particles = []
    raw_particles = table.get("particles", [])
    if isinstance(raw_particles, dict):
        raw_particles = [raw_particles]
    if not isinstance(raw_particles, list):
        raise ConfigError(f"{where}.particles must be a list of tables, got {raw_particles!r}")
    for i, sub in enumerate(raw_particles):
        name = f"{where}.particles[{i}]"
        args = _read_table(sub, _PARTICLE_KEYS, name, ("region", "count"))
        _default_n_max(args)
        key_for(args, _SEED_TAGS["particles"] + i)
        particles.append(_build(name, Particles, args))
    gratings = None
    if "gratings" in table:
        name = f"{where}.gratings"
        args = _read_table(table["gratings"], _GRATING_KEYS, name, ("count",))
        _default_n_max(args)
        key_for(args, _SEED_TAGS["gratings"])
        gratings = _build(name, Gratings, args)
    return _build(
        where,
        EyeAperture,
        {
            "pupil": pupil,
            "lids": lids,
            "upper_lashes": lashes["upper"],
            "lower_lashes": lashes["lower"],
            "particles": tuple(particles),
            "gratings": gratings,
        },
    )


def _plain(value: Any) -> Any:
    arr = np.asarray(value, dtype=float)
    return float(arr) if arr.ndim == 0 else [float(v) for v in arr]


def _component_table(component, keys: dict[str, str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, kind in keys.items():
        if kind == "key":
            out[key] = [int(v) for v in np.asarray(jax.random.key_data(component.key)).ravel()]
        elif kind in ("int", "str"):
            out[key] = getattr(component, key)
        else:
            out[key] = _plain(getattr(component, key))
    return out


def eye_to_config(eye: EyeAperture) -> dict[str, Any]:
    """The configuration table of an eye (inverse of :func:`eye_from_config`).

    Values are plain Python floats, ints, strings and lists (ready for TOML / JSON);
    every random component carries its `key_data`, so
    ``eye_from_config(eye_to_config(eye))`` rasterises identically. Stamp-window
    overrides are not written (they belong to a grid, not to the eye).
    """
    if not isinstance(eye, EyeAperture):
        raise ConfigError(f"eye_to_config needs an EyeAperture, got {type(eye).__name__}")
    table: dict[str, Any] = {"pupil": _component_table(eye.pupil, _PUPIL_KEYS)}
    if eye.lids is not None:
        table["lids"] = _component_table(eye.lids, _LIDS_KEYS)
    if eye.upper_lashes is not None:
        table["lashes_upper"] = _component_table(eye.upper_lashes, _LASH_KEYS)
    if eye.lower_lashes is not None:
        table["lashes_lower"] = _component_table(eye.lower_lashes, _LASH_KEYS)
    if eye.particles:
        table["particles"] = [_component_table(p, _PARTICLE_KEYS) for p in eye.particles]
    if eye.gratings is not None:
        table["gratings"] = _component_table(eye.gratings, _GRATING_KEYS)
    return table


# --------------------------------------------------------------------------------------
# presets


def _preset_key(key, tag: int) -> Key[Array, ""]:
    return jax.random.fold_in(as_key(key), tag)


def daylight_eye(key: Key[Array, ""] | int = 0) -> EyeAperture:
    """A bright-light eye: small pupil, slightly narrowed lids, lashes, a few cornea cells.

    - pupil: 3.0 mm, round, centred;
    - lids: upper opening 2.2 mm, lower 3.0 mm (a mild squint), no tilt, curvature
      0.04 /mm;
    - upper lashes: 40 (pool 48), length 2.5 mm, thickness 0.06 mm, spread 12 deg,
      jitter 0.5, curvature 0.05 /mm, span 8 mm;
    - lower lashes: 20 (pool 24), length 2.0 mm, thickness 0.05 mm, spread 15 deg,
      jitter 0.5, curvature -0.05 /mm, span 7 mm;
    - particles: 60 cornea cells (pool 64), radius 7.5 um (15 um cells), spread 0.2,
      over a disk of 5.5 mm.

    No gratings: the 1.5 mm pupil radius lies inside the lens cortex's annulus.
    `key` seeds every component (``fold_in(key, tag)``, as :func:`eye_from_config`).
    """
    return EyeAperture(
        pupil=Pupil(3.0),
        lids=Eyelids(2.2, 3.0, 0.0, 0.0, 0.04),
        upper_lashes=Eyelashes(
            count=40.0,
            n_max=48,
            key=_preset_key(key, _SEED_TAGS["lashes_upper"]),
            lid="upper",
            angular_spread_deg=12.0,
            thickness_mm=0.06,
            length_mm=2.5,
            curvature_per_mm=0.05,
            root_span_mm=8.0,
        ),
        lower_lashes=Eyelashes(
            count=20.0,
            n_max=24,
            key=_preset_key(key, _SEED_TAGS["lashes_lower"]),
            lid="lower",
            angular_spread_deg=15.0,
            thickness_mm=0.05,
            length_mm=2.0,
            curvature_per_mm=-0.05,
            root_span_mm=7.0,
        ),
        particles=(
            Particles(
                count=60.0,
                n_max=64,
                key=_preset_key(key, _SEED_TAGS["particles"]),
                region="cornea",
                radius_mean_mm=0.0075,
                radius_spread=0.2,
                region_radius_mm=5.5,
            ),
        ),
    )


def night_eye(key: Key[Array, ""] | int = 0) -> EyeAperture:
    """A dark-adapted eye: wide pupil, open lids, lens and vitreous particles, gratings.

    - pupil: 7.0 mm, round, centred;
    - lids: upper opening 4.5 mm, lower 4.0 mm, no tilt, curvature 0.04 /mm;
    - upper lashes: 80 (pool 96), length 3.0 mm, thickness 0.08 mm, spread 10 deg,
      jitter 0.5, curvature 0.05 /mm, span 9 mm;
    - lens nucleus: 750 particles (Ritschel et al.'s count), radius 10 um, spread 0.3,
      ball of 2.5 mm;
    - vitreous: 250 particles, radius 20 um, spread 0.3, ball of 6 mm;
    - gratings: 200 (Ritschel et al.'s count), 5 lines each, spacing 40 um, width
      12 um, length 0.3 mm, annulus 2.0-3.5 mm.

    `key` seeds every component (``fold_in(key, tag)``, as :func:`eye_from_config`).
    """
    return EyeAperture(
        pupil=Pupil(7.0),
        lids=Eyelids(4.5, 4.0, 0.0, 0.0, 0.04),
        upper_lashes=Eyelashes(
            count=80.0,
            n_max=96,
            key=_preset_key(key, _SEED_TAGS["lashes_upper"]),
            lid="upper",
            angular_spread_deg=10.0,
            thickness_mm=0.08,
            length_mm=3.0,
            curvature_per_mm=0.05,
            root_span_mm=9.0,
        ),
        particles=(
            Particles(
                count=750.0,
                n_max=750,
                key=_preset_key(key, _SEED_TAGS["particles"]),
                region="lens_nucleus",
                radius_mean_mm=0.01,
                radius_spread=0.3,
                region_radius_mm=2.5,
            ),
            Particles(
                count=250.0,
                n_max=250,
                key=_preset_key(key, _SEED_TAGS["particles"] + 1),
                region="vitreous",
                radius_mean_mm=0.02,
                radius_spread=0.3,
                region_radius_mm=6.0,
            ),
        ),
        gratings=Gratings(
            count=200.0,
            n_max=200,
            key=_preset_key(key, _SEED_TAGS["gratings"]),
            spacing_mm=0.04,
            line_thickness_mm=0.012,
            line_length_mm=0.3,
            inner_radius_mm=2.0,
            outer_radius_mm=3.5,
            lines_per_grating=5,
        ),
    )
