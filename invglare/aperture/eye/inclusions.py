"""What lies inside the eye, projected onto the pupil plane: particles and fibre gratings.

Cornea cells, lens-nucleus and vitreous particles (:class:`Particles`) and the
lens-fibre gratings of the lens cortex (:class:`Gratings`), after Ritschel et al.
(2009, sec. 3): relaxed-count pools of small opaque elements, stamped on local windows.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from invglare._core.checks import as_float, check_range, check_static_int, choose, is_concrete
from invglare._core.grids import ApertureGrid
from invglare.aperture._checks import check_finite
from invglare.aperture.eye.pool import AbstractPool, dtype_of, unit_draws
from invglare.aperture.shapes.stamps import disks_log_transmission, segments_log_transmission
from invglare.errors import PhysicsRangeError

#: Where a population of particles lives; see :class:`Particles`.
REGIONS = ("cornea", "lens_nucleus", "vitreous")

#: Standard-normal draws of particle radii are clipped to this many sigmas, so that the
#: largest radius (and with it the stamp window) is bounded.
_RADIUS_CLIP_SIGMA = 3.0


class Particles(AbstractPool):
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

    region: str = eqx.field(static=True, default="lens_nucleus")
    radius_mean_mm: Float[Array, ""] = eqx.field(converter=as_float, default=0.01)
    radius_spread: Float[Array, ""] = eqx.field(converter=as_float, default=0.3)
    region_radius_mm: Float[Array, ""] = eqx.field(converter=as_float, default=2.5)
    offsets_mm: Float[Array, "n_max 2"] | None = None
    stamp_bound_mm: float | None = eqx.field(static=True, default=None)
    stamp_half_px: int | None = eqx.field(static=True, default=None)

    @property
    def owner(self) -> str:
        return f"{self.region} particles"

    def __check_init__(self):
        choose("particles region", self.region, REGIONS)
        owner = self.owner
        if self.offsets_mm is not None:
            check_finite(f"{owner} offsets_mm", self.offsets_mm, (self.n_max, 2))
        check_range(f"{owner} radius_mean_mm", self.radius_mean_mm, 0.0, lo_open=True, unit="mm")
        check_range(f"{owner} radius_spread", self.radius_spread, 0.0)
        check_range(
            f"{owner} region_radius_mm", self.region_radius_mm, 0.0, lo_open=True, unit="mm"
        )

    def _draws(self):
        dtype = dtype_of(self.radius_mean_mm, self.region_radius_mm)
        return unit_draws(self.key, self.n_max, 2, 4, dtype)

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

    def stamp_bound(self) -> Float[Array, ""]:
        """Largest particle radius (mm)."""
        return jnp.max(self.radii_mm())

    def log_transmission(self, grid: ApertureGrid) -> Float[Array, "n n"]:
        """``log`` of the particles' transmission on `grid`."""
        return _particles_log(self, grid, self.window_half_px(grid))


class Gratings(AbstractPool):
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

    spacing_mm: Float[Array, ""] = eqx.field(converter=as_float, default=0.04)
    line_thickness_mm: Float[Array, ""] = eqx.field(converter=as_float, default=0.012)
    line_length_mm: Float[Array, ""] = eqx.field(converter=as_float, default=0.3)
    inner_radius_mm: Float[Array, ""] = eqx.field(converter=as_float, default=2.0)
    outer_radius_mm: Float[Array, ""] = eqx.field(converter=as_float, default=3.5)
    lines_per_grating: int = eqx.field(static=True, default=5)
    stamp_bound_mm: float | None = eqx.field(static=True, default=None)
    stamp_half_px: int | None = eqx.field(static=True, default=None)

    @property
    def owner(self) -> str:
        return "gratings"

    def __check_init__(self):
        check_static_int("gratings lines_per_grating", self.lines_per_grating, 1)
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
        dtype = dtype_of(self.spacing_mm, self.inner_radius_mm)
        u, _ = unit_draws(self.key, self.n_max, 2, 0, dtype)
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
        weights = jnp.repeat(self.weights(), lines_n)
        return starts, ends, weights

    def stamp_bound(self) -> Float[Array, ""]:
        """Half-extent (mm) of one line: half its length plus half its width."""
        return 0.5 * (self.line_length_mm + self.line_thickness_mm)

    def log_transmission(self, grid: ApertureGrid) -> Float[Array, "n n"]:
        """``log`` of the gratings' transmission on `grid`."""
        return _gratings_log(self, grid, self.window_half_px(grid))


# Jitted rasterisers of the stamped components (`half_px`, a Python int, is static): evaluated
# eagerly, their few dozen small operations would each be compiled and dispatched.


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
