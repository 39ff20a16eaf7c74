"""The tear film as a height field: a thin phase layer at the cornea (Novosad & Ziegler, 2.2).

The film's thickness ``d(x, y)`` delays the wave by ``Delta phi = k (eta - 1) d`` (``k =
2 pi / lambda``, ``eta`` the tear's refractive index, 1.337). Only the *variations* of ``d``
across the pupil matter; a uniform film is a constant phase.

Two static patterns, both sums of plane-wave modes evaluated at physical coordinates (so
that every colour's grid sees the same film):

- ``"sinusoid"``: the paper's, ``d = A sin(2 pi u / L) sin(2 pi v / L)`` with ``(u, v)``
  the grid axes rotated by `angle_deg`; `amplitude_um` is the peak ``A`` and `scale_mm`
  the period ``L``;
- ``"random"``: a smooth Gaussian random field, ``d = A sqrt(2 / K) sum_k cos(q_k . x +
  phi_k)`` with ``q_k = z_k / l``, ``z_k ~ N(0, I)``, ``phi_k ~ U[0, 2 pi)`` drawn once from
  `key`. Its covariance is exactly ``A^2 exp(-|r|^2 / (2 l^2))`` in expectation over the
  draw: `amplitude_um` is the rms height and `scale_mm` the correlation length ``l``; the
  rms slope is ``sqrt(2) A / l``. Smooth in both, so both are fittable.

**Animation** (`time_s`, seconds since the last blink): the irregularities grow as ``A (1 +
g t)`` (`irregularity_growth_per_s`), the film thins by evaporation to ``max(d0 - r t,
0)`` (`thickness_um`, `thinning_um_per_s`), and after `breakup_time_s` dry spots open at
`breakup_spots` random places within `breakup_region_mm` of the axis (each after its own
random delay of up to a second), their radius growing at `breakup_growth_mm_per_s`, their
rim a smooth step `breakup_edge_mm` wide; inside a spot the film is gone (``d = 0``).

**Sampling** (:meth:`TearFilm.check_sampled`): the film tilts rays by ``(eta - 1) |grad
d|``, so its phase is sampled on the holographic grid (``pitch = lambda / (N dt)``) when
``(eta - 1) max |grad d| <= N dt / 2``, whatever the wavelength: the grid must reach the
directions the film sends light into. Said as a pitch: ``pitch <= lambda / (2 (eta - 1)
max |grad d|)``.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Complex, Float, Key

from invglare._core.checks import as_float, check_range
from invglare._core.grids import ApertureGrid, nm_to_mm
from invglare.aperture.eye import smooth_step
from invglare.dynamics.noise import normal, uniform
from invglare.errors import ConfigError, PhysicsRangeError

__all__ = ["TEAR_PATTERNS", "TearFilm"]

#: The static height patterns of a tear film.
TEAR_PATTERNS = ("sinusoid", "random")
#: Refractive index of tears (about that of the aqueous humour).
TEAR_INDEX = 1.337

_MODE_TAG, _SPOT_TAG = 31, 32
#: Largest random delay (s) of a dry spot after the break-up time.
_SPOT_DELAY_S = 1.0


def _as_key(x) -> Key[Array, ""]:
    if isinstance(x, int | np.integer) and not isinstance(x, bool):
        return jax.random.key(int(x))
    arr = jnp.asarray(x)
    if jnp.issubdtype(arr.dtype, jax.dtypes.prng_key):
        return arr
    if arr.dtype == jnp.uint32:
        return jax.random.wrap_key_data(arr)
    raise ConfigError(f"tear film key must be a jax.random key, key data or an int, got {x!r}")


class TearFilm(eqx.Module):
    """A tear-film height field (see the module docstring for the patterns and animation).

    **Arguments:**

    - `amplitude_um`: peak (sinusoid) or rms (random) height variation (um, >= 0).
    - `scale_mm`: period (sinusoid) or correlation length (random), mm, > 0.
    - `key`: randomness of the random modes and of the dry spots (typed key, key data
      or int seed).
    - `pattern`: ``"sinusoid"`` or ``"random"`` (static).
    - `angle_deg`: rotation of the sinusoid's axes (deg).
    - `n_modes`: modes of the random field (static, >= 1; 64 by default).
    - `refractive_index`: the tear's index (static, 1.337).
    - `thickness_um`: mean film thickness (um, >= 0), what a dry spot removes.
    - `irregularity_growth_per_s`, `thinning_um_per_s`: growth of the irregularities
      (1/s) and evaporation rate (um/s), both >= 0.
    - `breakup_time_s`: when dry spots start to open (s, > 0; ``inf``: never).
    - `breakup_spots`: number of dry spots (static, >= 0).
    - `breakup_growth_mm_per_s`, `breakup_edge_mm`, `breakup_region_mm`: spot growth
      rate, rim width and the radius of the region they open in.

    **Example:**

    ```python
    film = TearFilm(0.1, 0.4, key=3, pattern="random")
    grid = ApertureGrid(256, 0.03)
    d_mm = film.height_mm(grid)               # (256, 256)
    t = film.transmission(grid, 550.0)        # exp(i k (eta - 1) d)
    ```
    """

    amplitude_um: Float[Array, ""] = eqx.field(converter=as_float)
    scale_mm: Float[Array, ""] = eqx.field(converter=as_float)
    key: Key[Array, ""] = eqx.field(converter=_as_key, default=0)
    pattern: str = eqx.field(static=True, default="sinusoid")
    angle_deg: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)
    n_modes: int = eqx.field(static=True, default=64)
    refractive_index: float = eqx.field(static=True, default=TEAR_INDEX)
    thickness_um: Float[Array, ""] = eqx.field(converter=as_float, default=7.0)
    irregularity_growth_per_s: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)
    thinning_um_per_s: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)
    breakup_time_s: Float[Array, ""] = eqx.field(converter=as_float, default=math.inf)
    breakup_spots: int = eqx.field(static=True, default=0)
    breakup_growth_mm_per_s: Float[Array, ""] = eqx.field(converter=as_float, default=0.05)
    breakup_edge_mm: Float[Array, ""] = eqx.field(converter=as_float, default=0.5)
    breakup_region_mm: Float[Array, ""] = eqx.field(converter=as_float, default=2.5)

    def __check_init__(self):
        if self.pattern not in TEAR_PATTERNS:
            raise ConfigError(
                f"tear film pattern = {self.pattern!r} is not one of {', '.join(TEAR_PATTERNS)}"
            )
        for name, value in (("n_modes", self.n_modes), ("breakup_spots", self.breakup_spots)):
            lo = 1 if name == "n_modes" else 0
            if not isinstance(value, int) or isinstance(value, bool) or value < lo:
                raise ConfigError(f"tear film {name} must be an integer >= {lo}, got {value!r}")
        if not (isinstance(self.refractive_index, float) and self.refractive_index >= 1.0):
            raise PhysicsRangeError(
                f"tear film refractive_index must be a float >= 1, got {self.refractive_index!r}"
            )
        check_range("tear film amplitude_um", self.amplitude_um, 0.0, unit="um")
        check_range("tear film scale_mm", self.scale_mm, 0.0, lo_open=True, unit="mm")
        check_range("tear film angle_deg", self.angle_deg, -math.inf)
        check_range("tear film thickness_um", self.thickness_um, 0.0, unit="um")
        check_range("tear film irregularity_growth_per_s", self.irregularity_growth_per_s, 0.0)
        check_range("tear film thinning_um_per_s", self.thinning_um_per_s, 0.0, unit="um/s")
        if not isinstance(self.breakup_time_s, jax.core.Tracer):
            t_bu = float(self.breakup_time_s)
            if not t_bu > 0 or math.isnan(t_bu):
                raise PhysicsRangeError(f"tear film breakup_time_s must be > 0, got {t_bu:g} s")
        check_range("tear film breakup_growth_mm_per_s", self.breakup_growth_mm_per_s, 0.0)
        check_range("tear film breakup_edge_mm", self.breakup_edge_mm, 0.0, lo_open=True)
        check_range("tear film breakup_region_mm", self.breakup_region_mm, 0.0)

    # -------------------------------------------------------------------- modes

    def _modes(self) -> tuple[Array, Array, Array, Array]:
        """Wave vectors (rad/mm), weights (mm) and phases of the plane-wave modes of the film."""
        dtype = jnp.result_type(self.amplitude_um, self.scale_mm, float)
        amp_mm = self.amplitude_um * 1e-3
        if self.pattern == "sinusoid":
            # sin(a u) sin(a v) = [cos(a (u - v)) - cos(a (u + v))] / 2, rotated by angle_deg.
            q = 2.0 * math.pi / self.scale_mm
            th = jnp.deg2rad(self.angle_deg)
            c, s = jnp.cos(th), jnp.sin(th)
            # u = c x + s y, v = -s x + c y
            u_vec = jnp.stack([c, s])
            v_vec = jnp.stack([-s, c])
            qs = jnp.stack([q * (u_vec - v_vec), q * (u_vec + v_vec)])
            weights = jnp.stack([0.5 * amp_mm, 0.5 * amp_mm])
            phases = jnp.asarray([0.0, math.pi], dtype)
            return qs[:, 0], qs[:, 1], weights, phases
        k_q, k_p = jax.random.split(jax.random.fold_in(self.key, _MODE_TAG))
        z = normal(k_q, (self.n_modes, 2), dtype)
        phases = uniform(k_p, (self.n_modes,), dtype, 0.0, 2.0 * math.pi)
        weights = jnp.full((self.n_modes,), math.sqrt(2.0 / self.n_modes), dtype) * amp_mm
        return z[:, 0] / self.scale_mm, z[:, 1] / self.scale_mm, weights, phases

    def _mode_sum(self, grid: ApertureGrid, factor_x: bool, factor_y: bool) -> Array:
        """``sum_k w_k (i qx)^a (i qy)^b exp(i (q_k . x + phi_k))`` (real part) on the grid.

        Written as two matrix products (modes are separable in x and y), so K modes cost
        ``2 K N^2`` multiply-adds instead of ``K N^2`` cosines.
        """
        qx, qy, w, phi = self._modes()
        c = grid.coords_mm()
        coef = w * jnp.exp(1j * phi)
        if factor_x:
            coef = coef * (1j * qx)
        if factor_y:
            coef = coef * (1j * qy)
        ex = jnp.exp(1j * c[:, None] * qx[None, :])  # (n, K): column coordinate x
        ey = jnp.exp(1j * c[:, None] * qy[None, :])  # (n, K): row coordinate y
        return jnp.real((ey * coef[None, :]) @ ex.T)

    # -------------------------------------------------------------------- dynamics

    def _state(self, time_s):
        t = as_float(time_s)
        scale = 1.0 + self.irregularity_growth_per_s * t
        mean_mm = jnp.maximum(self.thickness_um - self.thinning_um_per_s * t, 0.0) * 1e-3
        return t, scale, mean_mm

    def _spots(self, dtype):
        k_c, k_d = jax.random.split(jax.random.fold_in(self.key, _SPOT_TAG))
        u = uniform(k_c, (self.breakup_spots, 2), dtype)
        r = self.breakup_region_mm * jnp.sqrt(u[:, 0])
        ang = 2.0 * math.pi * u[:, 1]
        delay = uniform(k_d, (self.breakup_spots,), dtype, 0.0, _SPOT_DELAY_S)
        return r * jnp.cos(ang), r * jnp.sin(ang), delay

    def _dry(self, grid: ApertureGrid, t) -> tuple[Array, Array]:
        """Dry-spot coverage in [0, 1] and the magnitude of its gradient (1/mm)."""
        y, x = grid.mesh_mm()
        if self.breakup_spots == 0:
            zero = jnp.zeros_like(x)
            return zero, zero
        cx, cy, delay = self._spots(x.dtype)
        radius = self.breakup_growth_mm_per_s * jnp.maximum(t - self.breakup_time_s - delay, 0.0)
        # inf - inf would be nan when the break-up never comes: such spots have radius 0.
        radius = jnp.where(jnp.isfinite(self.breakup_time_s), radius, 0.0)
        dist = jnp.sqrt((x[None] - cx[:, None, None]) ** 2 + (y[None] - cy[:, None, None]) ** 2)
        edge = self.breakup_edge_mm
        s = (radius[:, None, None] - dist) / edge + 0.5
        # A spot exists once its radius exceeds half its rim: no faint disk before it opens.
        alive = (radius > 0.5 * edge)[:, None, None]
        cover = jnp.where(alive, smooth_step(s), 0.0)
        slope = jnp.where(alive & (s > 0) & (s < 1), 6.0 * s * (1.0 - s) / edge, 0.0)
        total = jnp.sum(cover, axis=0)
        return jnp.minimum(total, 1.0), jnp.where(total < 1.0, jnp.sum(slope, axis=0), 0.0)

    # -------------------------------------------------------------------- public

    def height_mm(self, grid: ApertureGrid, time_s: ArrayLike = 0.0) -> Float[Array, "n n"]:
        """The film's height ``d(x, y)`` (mm) at `time_s` on a centred grid."""
        t, scale, mean_mm = self._state(time_s)
        film = mean_mm + scale * self._mode_sum(grid, False, False)
        dry, _ = self._dry(grid, t)
        return film * (1.0 - dry)

    def slope(self, grid: ApertureGrid, time_s: ArrayLike = 0.0) -> Float[Array, "n n"]:
        """``|grad d|`` (dimensionless) on the grid, from the modes' derivatives in closed form.

        At a dry spot's rim the bound ``|grad d| <= |grad film| + film |grad dry|`` is used.
        """
        t, scale, mean_mm = self._state(time_s)
        gx = scale * self._mode_sum(grid, True, False)
        gy = scale * self._mode_sum(grid, False, True)
        film = mean_mm + scale * self._mode_sum(grid, False, False)
        dry, dry_slope = self._dry(grid, t)
        return jnp.hypot(gx, gy) * (1.0 - dry) + jnp.abs(film) * dry_slope

    def transmission(
        self, grid: ApertureGrid, wavelength_nm: ArrayLike, time_s: ArrayLike = 0.0
    ) -> Complex[Array, "n n"]:
        """``exp(i k (eta - 1) d)``: the film as a phase-only layer."""
        k = 2.0 * math.pi / nm_to_mm(wavelength_nm)
        phase = k * (self.refractive_index - 1.0) * self.height_mm(grid, time_s)
        return jnp.exp(1j * phase)

    def check_sampled(
        self, grid: ApertureGrid, wavelength_nm: float, times_s=(0.0,), radius_mm=None
    ) -> None:
        """Refuse a film whose phase the grid aliases (see the module docstring).

        Checked at every time of `times_s` (concrete values), over the disk of
        `radius_mm` (default the whole grid) where the film's light can reach the pupil.

        **Raises:** `PhysicsRangeError` with the steepest slope, the phase step per pixel
        and the pitch (and grid size for this window) the film would need.
        """
        y, x = grid.mesh_mm()
        inside = jnp.ones_like(x, bool) if radius_mm is None else (x * x + y * y <= radius_mm**2)
        worst = 0.0
        for t in np.atleast_1d(np.asarray(times_s, dtype=float)):
            s = jnp.where(inside, self.slope(grid, float(t)), 0.0)
            worst = max(worst, float(jnp.max(s)))
        lam = float(wavelength_nm) * 1e-6
        pitch = float(grid.pitch_mm)
        step = 2.0 * math.pi / lam * (self.refractive_index - 1.0) * worst * pitch
        if step > math.pi:
            need = lam / (2.0 * (self.refractive_index - 1.0) * worst)
            raise PhysicsRangeError(
                f"the tear film's phase changes by up to {step:.3g} rad per pixel (slope "
                f"{worst:.3g}) at {float(wavelength_nm):g} nm, above pi: the grid (pitch "
                f"{pitch * 1e3:.3g} um) aliases its angular spectrum. It needs a pitch <= "
                f"{need * 1e3:.3g} um (npix >= {math.ceil(float(grid.width_mm) / need)} for "
                "this window), or a smaller amplitude_um / larger scale_mm / wider "
                "breakup_edge_mm"
            )
