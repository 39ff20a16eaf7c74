"""The eyelashes: a relaxed-count row of curved lashes rooted along a lid margin."""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from invglare._core.checks import as_float, check_range, check_static_int, choose
from invglare._core.grids import ApertureGrid
from invglare.aperture._checks import check_finite
from invglare.aperture.eye.lash_layout import LashLayout, slot_positions
from invglare.aperture.eye.pool import AbstractPool, dtype_of, unit_draws
from invglare.aperture.eye.pupil import LIDS, Eyelids
from invglare.aperture.shapes.stamps import polyline_log_transmission
from invglare.errors import ConfigError


class Eyelashes(AbstractPool):
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
    - `layout`: a :class:`~invglare.aperture.eye.lash_layout.LashLayout` of ``n_max``
      lashes, or None (default). With a layout every lash is where the layout puts it
      (root, direction, length, width, curvature: per-lash parameters a fit can free,
      ``upper_lashes.layout.angle_deg[i]``) and the key draws nothing; the population
      parameters above are then those of the distribution the lashes come from (see
      :func:`~invglare.aperture.eye.lash_layout.layout_prior_terms`), and only `count`
      still changes the image, through the weights. :meth:`with_layout` freezes the
      current draw into a layout.
    - `stamp_bound_mm`, `stamp_half_px`: static stamp-window overrides (see
      :meth:`EyeAperture.with_stamp_windows`); leave them None for automatic windows.

    Lash `i` is present with weight ``smooth_step(count - i)``; the slots are
    ``span / max(count, 1)`` apart, so the lashes spread evenly at any count and
    move smoothly as it changes. Lashes are fully opaque. Each lash is a polyline
    stamped segment by segment (see
    :func:`invglare.aperture.shapes.stamps.polyline_log_transmission`): the cost is
    proportional to the lash's length in pixels times the window, not to the grid area.
    """

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
    layout: LashLayout | None = None
    stamp_bound_mm: float | None = eqx.field(static=True, default=None)
    stamp_half_px: int | None = eqx.field(static=True, default=None)

    @property
    def owner(self) -> str:
        return f"{self.lid} lashes"

    def __check_init__(self):
        owner = self.owner
        choose("lashes lid", self.lid, LIDS)
        check_static_int(f"{owner} segments", self.segments, 1)
        check_finite(f"{owner} mean_angle_deg", self.mean_angle_deg, ())
        check_range(f"{owner} angular_spread_deg", self.angular_spread_deg, 0.0, unit="deg")
        check_range(f"{owner} spacing_jitter", self.spacing_jitter, 0.0)
        check_range(f"{owner} thickness_mm", self.thickness_mm, 0.0, lo_open=True, unit="mm")
        check_range(f"{owner} length_mm", self.length_mm, 0.0, lo_open=True, unit="mm")
        check_finite(f"{owner} curvature_per_mm", self.curvature_per_mm, ())
        check_range(f"{owner} root_span_mm", self.root_span_mm, 0.0, lo_open=True, unit="mm")
        check_range(f"{owner} length_spread", self.length_spread, 0.0, 0.999)
        check_range(f"{owner} thickness_spread", self.thickness_spread, 0.0, 0.999)
        if self.layout is not None and self.layout.size != self.n_max:
            raise ConfigError(
                f"{owner} layout describes {self.layout.size} lashes; the pool holds "
                f"n_max = {self.n_max}"
            )

    def _draws(self):
        dtype = dtype_of(self.length_mm, self.thickness_mm, self.mean_angle_deg)
        u, z = unit_draws(self.key, self.n_max, 3, 1, dtype)
        length = self.length_mm * (1.0 + self.length_spread * (2.0 * u[:, 0] - 1.0))
        thickness = self.thickness_mm * (1.0 + self.thickness_spread * (2.0 * u[:, 1] - 1.0))
        return u[:, 2], z[:, 0], length, thickness

    def drawn_layout(self) -> LashLayout:
        """The layout the key draws at the current population parameters (module docstring)."""
        jitter_u, angle_z, length, thickness = self._draws()
        slots, spacing = slot_positions(self.count, self.root_span_mm, self.n_max, length.dtype)
        return LashLayout(
            root_mm=slots + self.spacing_jitter * spacing * (jitter_u - 0.5),
            angle_deg=self.mean_angle_deg + self.angular_spread_deg * angle_z,
            length_mm=length,
            thickness_mm=thickness,
            curvature_per_mm=jnp.broadcast_to(self.curvature_per_mm, length.shape),
        )

    def current_layout(self) -> LashLayout:
        """The layout the lashes are drawn with: :attr:`layout`, or else the key's draw."""
        return self.layout if self.layout is not None else self.drawn_layout()

    def with_layout(self, layout: LashLayout | None = None) -> Eyelashes:
        """A copy carrying `layout` (default: the current draw, frozen; same image)."""
        return dataclasses.replace(self, layout=self.drawn_layout() if layout is None else layout)

    def polylines(
        self, lids: Eyelids, shift_mm: ArrayLike = (0.0, 0.0)
    ) -> tuple[Float[Array, "n_max s+1 2"], Float[Array, " n_max"], Float[Array, " n_max"]]:
        """Vertices (mm), thickness (mm) and weight of every lash of the pool."""
        lay = self.current_layout()
        length = lay.length_mm
        roots, normals = lids.margin(self.lid, lay.root_mm, shift_mm)
        angle = jnp.arctan2(normals[:, 1], normals[:, 0]) + jnp.deg2rad(lay.angle_deg)
        d = jnp.stack([jnp.cos(angle), jnp.sin(angle)], -1)
        d_perp = jnp.stack([-d[:, 1], d[:, 0]], -1)
        s = jnp.linspace(0.0, 1.0, self.segments + 1, dtype=length.dtype)[None, :]
        s = s * length[:, None]
        bend = 0.5 * lay.curvature_per_mm[:, None] * s * s
        points = (
            roots[:, None, :] + s[..., None] * d[:, None, :] + bend[..., None] * d_perp[:, None]
        )
        return points, lay.thickness_mm, self.weights()

    def stamp_bound(self) -> Float[Array, ""]:
        """Largest half-extent (mm) of the pixels one lash segment claims.

        Half the segment's arc, plus its half-width, which a mitred joint stretches by
        ``tan(bend / 2)`` on the outside of a bend (`bend`, the turn between segments, is
        at most the curvature times a segment's arc). It does not depend on the lids, so
        a gradient through the lid opening needs no fixed window.
        """
        lay = self.current_layout()
        length, thickness, kappa = lay.length_mm, lay.thickness_mm, lay.curvature_per_mm
        arc = length * jnp.sqrt(1.0 + (kappa * length) ** 2) / self.segments
        bend = jnp.minimum(jnp.abs(kappa) * arc, 0.5 * math.pi)
        return jnp.max(0.5 * arc + 0.5 * thickness * (1.0 + jnp.tan(0.5 * bend)))

    def log_transmission(
        self, grid: ApertureGrid, lids: Eyelids, shift_mm: ArrayLike = (0.0, 0.0)
    ) -> Float[Array, "n n"]:
        """``log`` of the lashes' transmission on `grid` (<= 0)."""
        return _lashes_log(self, grid, lids, as_float(shift_mm), self.window_half_px(grid))


# Jitted rasterisers of the lashes (`half_px`, a Python int, is static): evaluated
# eagerly, its few dozen small operations would each be compiled and dispatched.


@eqx.filter_jit
def _lashes_log(
    lashes: Eyelashes, grid: ApertureGrid, lids: Eyelids, shift_mm: Array, half_px: int
) -> Array:
    points, thickness, weights = lashes.polylines(lids, shift_mm)
    return polyline_log_transmission(grid, points, thickness, weights, half_px)
