"""The vitreous humour as a damped rigid body shaken by saccades.

Ritschel et al. (2009, sec. 3.4): the vitreous is a viscoelastic gel (Zimmerman
1980); head movements and saccades accelerate it, it rotates and comes to rest by
strong damping. It is modelled as one rigid body whose state is an angle and an
angular velocity, driven by damped random "saccade" forces and integrated by forward
Euler; the particles sit at fixed places inside it.

**State.** The rotation is a small rotation vector ``theta`` (rad; axis times angle,
about the centre of the vitreous), its angular velocity ``omega`` (rad/s) and the
current saccade torque ``tau`` (rad/s^2). One step of length ``dt``:

- ``theta <- theta + dt omega``
- ``omega <- omega + dt (tau - c omega - k theta - alpha)``   (forward Euler, old values)
- ``tau <- tau exp(-dt / decay) + kick``

where a kick happens with probability ``rate dt`` per step and turns the body about a
random axis in the pupil plane (a saccade rotates the eye about a vertical or
horizontal axis, and the gel lags behind the eye wall). The elastic term ``k``
brings the gel back to rest. ``alpha`` is the observer's motion, the paper's other
external force: the angular acceleration (rad/s^2) of the head and eye, given per
frame (e.g. from a camera path); the gel, seen from the eye, turns the other way.

**Where the numbers come from.** Zimmerman (1980) found the vitreous *overdamped*
(after a displacement it creeps back to rest without swinging), so the defaults are
overdamped, ``c^2 > 4 k``: ``c = 4 /s``, ``k = 2 /s^2`` return the gel with time
constants of 0.3 s and 1.7 s. Those rates, and the saccades' rate (1 per second),
torque (2 rad/s^2) and decay (0.05 s), are chosen values that give a visible, slowly
settling drift of the vitreous particles; they are not fitted to Zimmerman's
measurements.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Key

from invglare._core.checks import as_float, check_range
from invglare.dynamics.noise import uniform
from invglare.errors import ConfigError


class VitreousState(eqx.Module):
    """Rotation vector (rad), angular velocity (rad/s) and saccade torque (rad/s^2), each (3,)."""

    angle_rad: Float[Array, " 3"]
    velocity_rad_s: Float[Array, " 3"]
    torque_rad_s2: Float[Array, " 3"]


def rotation_matrix(rotvec: Float[ArrayLike, " 3"]) -> Float[Array, "3 3"]:
    """The rotation of a rotation vector (Rodrigues), exact and smooth through 0."""
    w = as_float(rotvec)
    angle2 = jnp.sum(w * w)
    small = angle2 < 1e-8
    safe2 = jnp.where(small, 1.0, angle2)
    angle = jnp.sqrt(safe2)
    # Taylor series below 1e-4 rad keep the value and gradient exact at 0.
    a = jnp.where(small, 1.0 - angle2 / 6.0, jnp.sin(angle) / angle)
    b = jnp.where(small, 0.5 - angle2 / 24.0, (1.0 - jnp.cos(angle)) / safe2)
    zero = jnp.zeros_like(w[0])
    cross = jnp.array(
        [[zero, -w[2], w[1]], [w[2], zero, -w[0]], [-w[1], w[0], zero]], dtype=w.dtype
    )
    return jnp.eye(3, dtype=w.dtype) + a * cross + b * (cross @ cross)


class VitreousBody(eqx.Module):
    """Parameters of the vitreous rigid body.

    **Arguments:**

    - `damping_per_s`: angular velocity damping ``c`` (1/s, >= 0); after a kick the
      velocity decays as ``exp(-c t)`` (without elasticity).
    - `stiffness_per_s2`: elastic return ``k`` (1/s^2, >= 0); ``c^2 > 4 k`` is the
      overdamped gel Zimmerman (1980) measured (the default), below it the gel swings.
    - `saccade_rate_hz`: mean number of saccade kicks per second (>= 0).
    - `saccade_strength_rad_s2`: torque of one kick (rad/s^2, >= 0).
    - `saccade_decay_s`: time constant of a kick's torque (s, > 0).

    **Example:**

    ```python
    body = VitreousBody()
    s = body.step(body.init_state(), jax.random.key(0), 1 / 30)
    moved = body.rotate(s, jnp.array([[1.0, 0.0, 3.0]]))  # a particle 3 mm behind the centre
    ```
    """

    damping_per_s: Float[Array, ""] = eqx.field(converter=as_float, default=4.0)
    stiffness_per_s2: Float[Array, ""] = eqx.field(converter=as_float, default=2.0)
    saccade_rate_hz: Float[Array, ""] = eqx.field(converter=as_float, default=1.0)
    saccade_strength_rad_s2: Float[Array, ""] = eqx.field(converter=as_float, default=2.0)
    saccade_decay_s: Float[Array, ""] = eqx.field(converter=as_float, default=0.05)

    def __check_init__(self):
        check_range("vitreous damping_per_s", self.damping_per_s, 0.0, unit="1/s")
        check_range("vitreous stiffness_per_s2", self.stiffness_per_s2, 0.0, unit="1/s^2")
        check_range("vitreous saccade_rate_hz", self.saccade_rate_hz, 0.0, unit="Hz")
        check_range("vitreous saccade_strength_rad_s2", self.saccade_strength_rad_s2, 0.0)
        check_range("vitreous saccade_decay_s", self.saccade_decay_s, 0.0, lo_open=True, unit="s")

    def init_state(self, dtype=None) -> VitreousState:
        """The body at rest."""
        z = jnp.zeros(3, dtype=dtype or self.damping_per_s.dtype)
        return VitreousState(z, z, z)

    def check_time_step(self, dt_s: float) -> None:
        """Raise `ConfigError` when forward Euler would be unstable at steps of `dt_s`.

        The step multiplies the free motion's modes by ``1 + dt lambda`` with
        ``lambda**2 + c lambda + k = 0``; it is stable while ``|1 + dt lambda| < 1``, and a
        kick must fit at least once in its decay.
        """
        c, k = float(self.damping_per_s), float(self.stiffness_per_s2)
        lams = np.roots([1.0, c, k]) if k > 0 else np.array([-c])
        growth = float(np.max(np.abs(1.0 + dt_s * lams)))
        if growth >= 1.0 and (c > 0 or k > 0):
            raise ConfigError(
                f"vitreous forward Euler is unstable at steps of {dt_s * 1e3:.4g} ms for "
                f"damping_per_s = {c:g}, stiffness_per_s2 = {k:g} (mode growth {growth:.3f} "
                "per step); raise the frame rate or lower the damping and stiffness"
            )
        if float(self.saccade_rate_hz) * dt_s > 1.0:
            raise ConfigError(
                f"vitreous saccade_rate_hz = {float(self.saccade_rate_hz):g} exceeds one kick per "
                f"frame ({1 / dt_s:.4g} frames/s)"
            )

    def step(
        self,
        state: VitreousState,
        key: Key[Array, ""],
        dt_s: float | ArrayLike,
        head_acceleration_rad_s2: Float[ArrayLike, " 3"] | None = None,
    ) -> VitreousState:
        """Advance by `dt_s` (forward Euler); `key` decides this step's saccade.

        `head_acceleration_rad_s2`: the observer's angular acceleration during the step
        (rad/s^2, a rotation-vector rate: x, y in the pupil plane, z along the axis),
        which drives the gel the other way; None: a still head.
        """
        dt = as_float(dt_s)
        k_hit, k_dir = jax.random.split(key)
        dtype = state.velocity_rad_s.dtype
        hit = uniform(k_hit, (), dtype) < self.saccade_rate_hz * dt
        phi = uniform(k_dir, (), dtype, 0.0, 2.0 * math.pi)
        axis = jnp.stack([jnp.cos(phi), jnp.sin(phi), jnp.zeros_like(phi)])
        kick = jnp.where(hit, self.saccade_strength_rad_s2, 0.0) * axis
        theta, omega, tau = state.angle_rad, state.velocity_rad_s, state.torque_rad_s2
        accel = tau - self.damping_per_s * omega - self.stiffness_per_s2 * theta
        if head_acceleration_rad_s2 is not None:
            accel = accel - jnp.broadcast_to(as_float(head_acceleration_rad_s2), (3,))
        return VitreousState(
            theta + dt * omega,
            omega + dt * accel,
            tau * jnp.exp(-dt / self.saccade_decay_s) + kick,
        )

    def rotate(
        self, state: VitreousState, points_mm: Float[ArrayLike, "m 3"]
    ) -> Float[Array, "m 3"]:
        """Points fixed in the body (rest coordinates, mm, about its centre) after the rotation."""
        return jnp.asarray(points_mm) @ rotation_matrix(state.angle_rad).T
