"""The crystalline lens as a 17 x 17 mass-spring mesh, deformed by the ciliary muscle.

Ritschel et al. (2009, sec. 3.3) move the lens-nucleus particles with a simplified
deformation of a radially symmetric lens: a coarse mass-spring grid over the lens's
meridional cross-section, one element of which is moved by the accommodation signal
(the ciliary muscle's contraction), and a bilinear interpolation of the grid's
displacement carrying every particle, stored in cylindrical coordinates
``(rho, z, phi)``.

**Geometry.** The lens is a spheroid of equatorial radius `radius_mm` (``a``) and
half-thickness `half_thickness_mm` (``b``). The mesh covers the half cross-section
``0 <= rho <= a``, ``-b <= z <= b`` with `nodes` x `nodes` nodes, row ``i`` at
``z = -b + 2 b i / (nodes - 1)`` and column ``j`` at ``rho = a j / (nodes - 1)``.
Nodes are joined to their 8 neighbours by springs (4 axial, 4 diagonal) of equal
stiffness and tied to their rest places by weak anchor springs (the capsule's
elasticity, which also keeps the mesh from drifting); velocities are damped.

**Boundary conditions.** The axis column keeps ``rho = 0`` (radial symmetry). The
node at the equator (``rho = a``, ``z = 0``) is the ciliary element: it is placed at
``a - equator_mm_per_diopter * accommodation``, so positive accommodation (the muscle
contracting, the lens rounding up) pulls the equator in.

**Integration.** Semi-implicit (symplectic) Euler with `substeps` steps per frame;
:meth:`LensMesh.check_time_step` refuses frame times at which it would be unstable.

**Where the numbers come from.** The 17 x 17 mesh, the single moving element and the
bilinear carrying of the particles are the paper's. The lens's size (``a = 4.5`` mm,
``b = 2.0`` mm: an adult lens about 9 mm across and 4 mm thick) is textbook anatomy;
the spring stiffness (1400 /s^2), anchor ratio (0.02), damping (20 /s) and the
equator's travel (0.05 mm per dioptre) are chosen values (the paper calls its springs
"heuristic"): with them a pull crosses the lens in a few tenths of a second and a few
hundredths of a dioptre move particles by microns.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from invglare._core.checks import as_float, check_range
from invglare._core.maths import safe_sqrt
from invglare.errors import ConfigError

# The 4 spring directions (row, column offsets); with their opposites, the 8 neighbours.
_SPRINGS = ((0, 1), (1, 0), (1, 1), (1, -1))


class LensState(eqx.Module):
    """Node positions and velocities of the mesh, ``(nodes, nodes, 2)`` as ``(rho, z)`` mm."""

    positions_mm: Float[Array, "n n 2"]
    velocities_mm_s: Float[Array, "n n 2"]


def _pair_slices(n: int, di: int, dj: int) -> tuple[tuple[slice, slice], tuple[slice, slice]]:
    """Index ranges of the two ends of every spring with offset (di, dj) on an n x n mesh."""
    a_rows, b_rows = slice(0, n - di), slice(di, n)
    if dj >= 0:
        a_cols, b_cols = slice(0, n - dj), slice(dj, n)
    else:
        a_cols, b_cols = slice(-dj, n), slice(0, n + dj)
    return (a_rows, a_cols), (b_rows, b_cols)


class LensMesh(eqx.Module):
    """Parameters of the lens mesh.

    **Arguments:**

    - `radius_mm`: equatorial radius ``a`` of the lens (mm, > 0); 4.5.
    - `half_thickness_mm`: half the axial thickness ``b`` (mm, > 0); 2.0.
    - `stiffness_per_s2`: spring stiffness over node mass (1/s^2, > 0).
    - `anchor_ratio`: stiffness of the anchor springs relative to the mesh springs
      (>= 0); small values let the deformation spread through the whole lens.
    - `damping_per_s`: velocity damping (1/s, >= 0).
    - `equator_mm_per_diopter`: inward motion of the equator per dioptre of
      accommodation (mm/D).
    - `nodes`: static mesh size per side (odd, >= 3); 17 as in the paper.
    - `substeps`: static integration steps per frame (>= 1).

    **Example:**

    ```python
    lens = LensMesh()
    state = lens.init_state()
    state = lens.step(state, lambda t: 0.01, 0.0, 1 / 30)  # equator pulled 10 um inwards
    rho, z = lens.deform(state, jnp.array([1.0]), jnp.array([0.5]))
    ```
    """

    radius_mm: Float[Array, ""] = eqx.field(converter=as_float, default=4.5)
    half_thickness_mm: Float[Array, ""] = eqx.field(converter=as_float, default=2.0)
    stiffness_per_s2: Float[Array, ""] = eqx.field(converter=as_float, default=1400.0)
    anchor_ratio: Float[Array, ""] = eqx.field(converter=as_float, default=0.02)
    damping_per_s: Float[Array, ""] = eqx.field(converter=as_float, default=20.0)
    equator_mm_per_diopter: Float[Array, ""] = eqx.field(converter=as_float, default=0.05)
    nodes: int = eqx.field(static=True, default=17)
    substeps: int = eqx.field(static=True, default=8)

    def __check_init__(self):
        check_range("lens radius_mm", self.radius_mm, 0.0, lo_open=True, unit="mm")
        check_range("lens half_thickness_mm", self.half_thickness_mm, 0.0, lo_open=True, unit="mm")
        check_range("lens stiffness_per_s2", self.stiffness_per_s2, 0.0, lo_open=True, unit="1/s^2")
        check_range("lens anchor_ratio", self.anchor_ratio, 0.0)
        check_range("lens damping_per_s", self.damping_per_s, 0.0, unit="1/s")
        check_range("lens equator_mm_per_diopter", self.equator_mm_per_diopter, -math.inf)
        for name, value, lo in (("nodes", self.nodes, 3), ("substeps", self.substeps, 1)):
            if not isinstance(value, int) or isinstance(value, bool) or value < lo:
                raise ConfigError(f"lens {name} must be an integer >= {lo}, got {value!r}")
        if self.nodes % 2 == 0:
            raise ConfigError(
                f"lens nodes must be odd (a node sits at the equator), got {self.nodes}"
            )

    # -- geometry ------------------------------------------------------------------

    def rest_positions_mm(self) -> Float[Array, "n n 2"]:
        """Rest ``(rho, z)`` of every node (mm), rows along z, columns along rho."""
        s = jnp.linspace(0.0, 1.0, self.nodes, dtype=self.radius_mm.dtype)
        rho = self.radius_mm * s
        z = self.half_thickness_mm * (2.0 * s - 1.0)
        return jnp.stack(jnp.broadcast_arrays(rho[None, :], z[:, None]), axis=-1)

    def half_height_mm(self, rho_mm: Float[ArrayLike, "*shape"]) -> Float[Array, "*shape"]:
        """Half the lens's axial thickness at radius `rho_mm` (0 beyond the equator)."""
        q = jnp.asarray(rho_mm) / self.radius_mm
        return self.half_thickness_mm * safe_sqrt(1.0 - q * q)

    def inside(self, rho_mm: ArrayLike, z_mm: ArrayLike) -> Array:
        """Whether points ``(rho, z)`` lie inside the rest lens (boolean)."""
        rho, z = jnp.asarray(rho_mm), jnp.asarray(z_mm)
        return (rho / self.radius_mm) ** 2 + (z / self.half_thickness_mm) ** 2 <= 1.0

    # -- dynamics ------------------------------------------------------------------

    def init_state(self) -> LensState:
        """The mesh at rest."""
        x0 = self.rest_positions_mm()
        return LensState(x0, jnp.zeros_like(x0))

    def max_stable_step_s(self) -> float:
        """Largest substep (s) at which the undamped mesh is stable (concrete parameters).

        Each node has at most 8 springs, so by Gershgorin the stiffness matrix's largest
        eigenvalue is at most ``16 k (1 + anchor)``; symplectic Euler is stable while
        ``dt * omega_max < 2``.
        """
        k = float(self.stiffness_per_s2) * (1.0 + float(self.anchor_ratio))
        return 2.0 / (4.0 * math.sqrt(k))

    def check_time_step(self, frame_s: float) -> None:
        """Raise `ConfigError` when `frame_s / substeps` exceeds :meth:`max_stable_step_s`."""
        limit = self.max_stable_step_s()
        if frame_s / self.substeps > limit:
            need = math.ceil(frame_s / limit)
            raise ConfigError(
                f"lens substeps = {self.substeps} is too few for frames of {frame_s * 1e3:.4g} ms: "
                f"steps of {frame_s / self.substeps * 1e3:.3g} ms exceed the stable "
                f"{limit * 1e3:.3g} ms of stiffness_per_s2 = {float(self.stiffness_per_s2):g}; "
                f"use substeps >= {need}"
            )

    def _forces(self, x: Array, v: Array, x0: Array) -> Array:
        n = self.nodes
        k = self.stiffness_per_s2
        force = -k * self.anchor_ratio * (x - x0) - self.damping_per_s * v
        for di, dj in _SPRINGS:
            sa, sb = _pair_slices(n, di, dj)
            d = x[sb] - x[sa]
            d0 = x0[sb] - x0[sa]
            length = jnp.sqrt(jnp.sum(d * d, axis=-1, keepdims=True))
            rest = jnp.sqrt(jnp.sum(d0 * d0, axis=-1, keepdims=True))
            # Hooke's law along the spring; at rest the stretch is exactly 0.
            f = k * (length - rest) * d / length
            force = force.at[sa].add(f).at[sb].add(-f)
        return force

    def _constrain(self, x: Array, v: Array, x0: Array, equator_shift_mm: Array):
        c = self.nodes // 2
        x = x.at[:, 0, 0].set(0.0)
        v = v.at[:, 0, 0].set(0.0)
        x = x.at[c, -1].set(
            x0[c, -1] + jnp.stack([-equator_shift_mm, jnp.zeros_like(equator_shift_mm)])
        )
        v = v.at[c, -1].set(0.0)
        return x, v

    def step(
        self,
        state: LensState,
        accommodation_d: Callable[[Array], Array],
        t_s: Float[ArrayLike, ""],
        dt_s: float | Float[ArrayLike, ""],
    ) -> LensState:
        """Advance the mesh from `t_s` by `dt_s`, driven by `accommodation_d(t)` (dioptres).

        `accommodation_d` is evaluated at the end of every substep; the equator node is
        placed at ``-equator_mm_per_diopter * accommodation`` from its rest place.
        """
        x0 = self.rest_positions_mm()
        h = as_float(dt_s) / self.substeps
        t0 = as_float(t_s)

        def substep(i, xv):
            x, v = xv
            v = v + h * self._forces(x, v, x0)
            x = x + h * v
            shift = self.equator_mm_per_diopter * accommodation_d(t0 + (i + 1) * h)
            return self._constrain(x, v, x0, shift)

        x, v = jax.lax.fori_loop(
            0, self.substeps, substep, (state.positions_mm, state.velocities_mm_s)
        )
        return LensState(x, v)

    # -- particles -----------------------------------------------------------------

    def deform(
        self, state: LensState, rho_mm: Float[ArrayLike, " m"], z_mm: Float[ArrayLike, " m"]
    ) -> tuple[Float[Array, " m"], Float[Array, " m"]]:
        """Deformed ``(rho, z)`` of points by bilinear interpolation of the mesh displacement.

        Points outside the mesh take the displacement of its nearest edge.
        """
        n = self.nodes
        rho, z = jnp.asarray(rho_mm), jnp.asarray(z_mm)
        disp = state.positions_mm - self.rest_positions_mm()
        gx = jnp.clip(rho / self.radius_mm * (n - 1), 0.0, n - 1.0)
        gy = jnp.clip((z / self.half_thickness_mm + 1.0) * 0.5 * (n - 1), 0.0, n - 1.0)
        j0 = jnp.clip(jnp.floor(gx), 0, n - 2)
        i0 = jnp.clip(jnp.floor(gy), 0, n - 2)
        fx = (gx - j0)[..., None]
        fy = (gy - i0)[..., None]
        j0 = j0.astype(jnp.int32)
        i0 = i0.astype(jnp.int32)
        d00, d01 = disp[i0, j0], disp[i0, j0 + 1]
        d10, d11 = disp[i0 + 1, j0], disp[i0 + 1, j0 + 1]
        d = (1 - fy) * ((1 - fx) * d00 + fx * d01) + fy * ((1 - fx) * d10 + fx * d11)
        return rho + d[..., 0], z + d[..., 1]
