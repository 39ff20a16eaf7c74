"""The whole dynamic eye: one state advanced frame by frame, and the numbers of each frame.

:class:`EyeDynamics` bundles the five moving parts (pupil, accommodation, lens,
vitreous, lids). Its state, :class:`DynamicsState`, is what a `lax.scan` carries from
frame to frame: time, the damped field luminance, the lens mesh and the vitreous body.
:meth:`EyeDynamics.values` turns a state into the numbers that shape that frame's
aperture (:class:`FrameValues`): pupil diameter, lid open fraction, lens deformation and
vitreous rotation. Nothing here knows about apertures; the temporal glare model
(:mod:`invglare.models.temporal`) applies the numbers to an eye.

Randomness is explicit: one key, from which every part derives its own by
``fold_in``; the step of frame ``n`` uses ``fold_in(key, n)``, so a sequence is a pure
function of (key, parameters, luminances).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Int, Key

from invglare._core.checks import as_float, check_range
from invglare.dynamics.accommodation import Accommodation
from invglare.dynamics.lens import LensMesh, LensState
from invglare.dynamics.lids import LidMotion
from invglare.dynamics.pupil import PupilDynamics, damp_luminance
from invglare.dynamics.vitreous import VitreousBody, VitreousState, rotation_matrix

_HIPPUS, _ACCOMMODATION, _VITREOUS, _LIDS = 1, 2, 3, 4


class DynamicsState(eqx.Module):
    """What carries over from one frame to the next.

    - `frame`: frame index (int32).
    - `time_s`: time of this frame (s).
    - `field_luminance_cd_m2`: the time-damped field luminance the pupil adapts to.
    - `lens`: the lens mesh (:class:`~invglare.dynamics.lens.LensState`).
    - `vitreous`: the vitreous body (:class:`~invglare.dynamics.vitreous.VitreousState`).
    """

    frame: Int[Array, ""]
    time_s: Float[Array, ""]
    field_luminance_cd_m2: Float[Array, ""]
    lens: LensState
    vitreous: VitreousState


class FrameValues(eqx.Module):
    """The numbers that shape one frame's aperture.

    - `time_s`: the frame's time (s).
    - `mean_pupil_mm`: eq. 2's mean diameter (or the rest diameter), mm.
    - `pupil_mm`: the diameter under the hippus, eq. 1, mm.
    - `lid_open_fraction`: lid opening relative to rest, in ``[0, 1]``.
    - `accommodation_d`: the accommodation fluctuation (D).
    - `lens`: the deformed lens mesh.
    - `vitreous_rotation`: ``(3, 3)`` rotation of the vitreous body.
    """

    time_s: Float[Array, ""]
    mean_pupil_mm: Float[Array, ""]
    pupil_mm: Float[Array, ""]
    lid_open_fraction: Float[Array, ""]
    accommodation_d: Float[Array, ""]
    lens: LensState
    vitreous_rotation: Float[Array, "3 3"]


class EyeDynamics(eqx.Module):
    """Parameters of every moving part of the eye.

    **Arguments:**

    - `pupil`: :class:`~invglare.dynamics.pupil.PupilDynamics` (eq. 1 and 2).
    - `accommodation`: :class:`~invglare.dynamics.accommodation.Accommodation`.
    - `lens`: :class:`~invglare.dynamics.lens.LensMesh`.
    - `vitreous`: :class:`~invglare.dynamics.vitreous.VitreousBody`.
    - `lids`: :class:`~invglare.dynamics.lids.LidMotion`.

    **Example:**

    ```python
    dyn = EyeDynamics()
    key = jax.random.key(0)
    state = dyn.init_state(100.0)                       # adapted to 100 cd/m^2
    values = dyn.values(state, key, rest_pupil_mm=4.0)  # frame 0
    state = dyn.step(state, 100.0, 1 / 30, key, 4.0)    # on to frame 1
    ```
    """

    pupil: PupilDynamics = eqx.field(default_factory=PupilDynamics)
    accommodation: Accommodation = eqx.field(default_factory=Accommodation)
    lens: LensMesh = eqx.field(default_factory=LensMesh)
    vitreous: VitreousBody = eqx.field(default_factory=VitreousBody)
    lids: LidMotion = eqx.field(default_factory=LidMotion)

    @classmethod
    def frozen(cls, lens: LensMesh | None = None) -> EyeDynamics:
        """Dynamics in which nothing moves: the eye stays exactly as configured.

        No hippus, no accommodation fluctuation (so the lens stays at rest), no saccades,
        no blinks, no squint, and the mean pupil is the eye's own diameter.
        """
        return cls(
            pupil=PupilDynamics(hippus_amplitude_mm=0.0, from_luminance=False),
            accommodation=Accommodation(low_d_per_mm=0.0, high_rms_d=0.0),
            lens=LensMesh() if lens is None else lens,
            vitreous=VitreousBody(saccade_rate_hz=0.0),
            lids=LidMotion(interval_s=0.0, squint=0.0),
        )

    def check_time_step(self, dt_s: float) -> None:
        """Refuse a frame time at which the lens or vitreous integration is unstable."""
        self.lens.check_time_step(dt_s)
        self.vitreous.check_time_step(dt_s)

    def init_state(
        self, field_luminance_cd_m2: float | Float[ArrayLike, ""] = 1.0, t0_s: float = 0.0
    ) -> DynamicsState:
        """The eye at rest, adapted to `field_luminance_cd_m2`, at time `t0_s`."""
        check_range("field luminance", field_luminance_cd_m2, 0.0, unit="cd/m^2")
        dtype = self.lens.radius_mm.dtype
        return DynamicsState(
            frame=jnp.asarray(0, jnp.int32),
            time_s=jnp.asarray(t0_s, dtype),
            field_luminance_cd_m2=jnp.asarray(field_luminance_cd_m2, dtype),
            lens=self.lens.init_state(),
            vitreous=self.vitreous.init_state(dtype),
        )

    def values(
        self, state: DynamicsState, key: Key[Array, ""], rest_pupil_mm: Float[ArrayLike, ""]
    ) -> FrameValues:
        """The numbers of the frame `state` is at.

        `rest_pupil_mm` is the eye's own pupil diameter: the mean when the pupil does not
        follow the luminance.
        """
        t = state.time_s
        mean = self.pupil.mean_diameter_mm(state.field_luminance_cd_m2, rest_pupil_mm)
        return FrameValues(
            time_s=t,
            mean_pupil_mm=mean,
            pupil_mm=self.pupil.diameter_mm(t, mean, jax.random.fold_in(key, _HIPPUS)),
            lid_open_fraction=self.lids.open_fraction(t, jax.random.fold_in(key, _LIDS)),
            accommodation_d=self.accommodation.signal_d(
                t, jax.random.fold_in(key, _ACCOMMODATION), mean
            ),
            lens=state.lens,
            vitreous_rotation=rotation_matrix(state.vitreous.angle_rad),
        )

    def step(
        self,
        state: DynamicsState,
        frame_luminance_cd_m2: Float[ArrayLike, ""],
        dt_s: float | Float[ArrayLike, ""],
        key: Key[Array, ""],
        rest_pupil_mm: Float[ArrayLike, ""],
        head_acceleration_rad_s2: Float[ArrayLike, " 3"] | None = None,
    ) -> DynamicsState:
        """Advance by one frame of `dt_s` seconds, after a frame of mean luminance given.

        The lens is driven by the accommodation signal of the frame's mean pupil; the
        vitreous by this frame's saccade draw and the observer's motion,
        `head_acceleration_rad_s2` (rad/s^2, ``(3,)``; None: a still head).
        """
        dt = as_float(dt_s)
        mean = self.pupil.mean_diameter_mm(state.field_luminance_cd_m2, rest_pupil_mm)
        k_acc = jax.random.fold_in(key, _ACCOMMODATION)
        lens = self.lens.step(
            state.lens, lambda t: self.accommodation.signal_d(t, k_acc, mean), state.time_s, dt
        )
        k_vit = jax.random.fold_in(jax.random.fold_in(key, _VITREOUS), state.frame)
        vitreous = self.vitreous.step(state.vitreous, k_vit, dt, head_acceleration_rad_s2)
        luminance = damp_luminance(
            state.field_luminance_cd_m2, frame_luminance_cd_m2, dt, self.pupil.adaptation_time_s
        )
        return DynamicsState(
            frame=state.frame + 1,
            time_s=state.time_s + dt,
            field_luminance_cd_m2=luminance.astype(state.field_luminance_cd_m2.dtype),
            lens=lens,
            vitreous=vitreous,
        )
