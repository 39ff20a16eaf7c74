"""Pupil size over time: Moon-Spencer adaptation (eq. 2) and the pupillary hippus (eq. 1).

Ritschel et al. (2009, sec. 3.2):

- the **mean** pupil diameter follows the field luminance ``L`` (cd/m^2) as Moon and
  Spencer (1944) proposed,
  ``p = 4.9 - 3 tanh(0.4 (log10 L + 1))`` mm, from 7.9 mm in the dark to 1.9 mm in
  bright light (eq. 2); the field luminance is a time-damped average of the frames'
  mean luminance (Durand and Dorsey 2000);
- the **hippus** makes the diameter fluctuate about that mean,
  ``h(t, p) = p + noise(t / p) (p_max / p) sqrt(1 - p / p_max)`` (eq. 1), with three
  octaves of value noise and ``p_max = 9`` mm: the smaller (brighter) the pupil, the
  faster and the larger the fluctuation.

The paper leaves the noise's scale open; here ``noise`` is value noise in ``[-1, 1]``
times `hippus_amplitude_mm`, so the fluctuation stays within
``amplitude * (p_max / p) sqrt(1 - p / p_max)`` of the mean (about +-0.42 mm at 1.9 mm
and +-0.04 mm at 7.9 mm with the default 0.1 mm).

**Where the numbers come from.** Eq. 2 (Moon and Spencer 1944), eq. 1 with
``p_max = 9`` mm and three octaves of value noise are the paper's; eq. 1's form is the
paper's fit to Fry's (1991) pupil recordings under discomfort glare. The noise's scale
(``hippus_amplitude_mm = 0.1``) is a chosen value (fluctuations of a few tenths of a mm
in bright light, as Fry's curves show qualitatively), and so is the time constant of
the damped field luminance (``adaptation_time_s = 0.5`` s; the paper damps the screen's
mean intensity after Durand and Dorsey 2000 without giving one).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Key

from invglare._core.checks import as_float, check_range, is_concrete
from invglare.dynamics.noise import value_noise

#: Largest pupil diameter of eq. 1 (mm).
P_MAX_MM = 9.0
#: The range of eq. 2: its limits in the dark and in bright light (mm).
MOON_SPENCER_RANGE_MM = (1.9, 7.9)
#: Luminances below this (cd/m^2) count as this: eq. 2 has a log, and is flat there anyway.
_MIN_LUMINANCE_CD_M2 = 1e-12



def moon_spencer_diameter_mm(luminance_cd_m2: Float[ArrayLike, "*shape"]) -> Float[Array, "*shape"]:
    """Mean pupil diameter (mm) for a field luminance, eq. 2 (Moon and Spencer 1944).

    **Arguments:**

    - `luminance_cd_m2`: field luminance (cd/m^2, >= 0; 0 is the dark limit).

    **Returns:** ``4.9 - 3 tanh(0.4 (log10 L + 1))``, between 1.9 and 7.9 mm.

    **Example:**

    ```python
    moon_spencer_diameter_mm(0.1)  # 4.9 mm: log10 L + 1 = 0
    ```
    """
    check_range("field luminance", luminance_cd_m2, 0.0, unit="cd/m^2")
    lum = jnp.maximum(as_float(luminance_cd_m2), _MIN_LUMINANCE_CD_M2)
    return 4.9 - 3.0 * jnp.tanh(0.4 * (jnp.log10(lum) + 1.0))


def hippus_scale(
    mean_diameter_mm: Float[ArrayLike, "*shape"], max_diameter_mm: float | Array = P_MAX_MM
) -> Float[Array, "*shape"]:
    """The factor ``(p_max / p) sqrt(1 - p / p_max)`` of eq. 1 (grows as the pupil shrinks)."""
    p = as_float(mean_diameter_mm)
    q = p / max_diameter_mm
    return jnp.sqrt(jnp.maximum(1.0 - q, 0.0)) / q


def hippus_diameter_mm(
    t_s: Float[ArrayLike, "*shape"],
    mean_diameter_mm: Float[ArrayLike, "*shape"],
    key: Key[Array, ""],
    amplitude_mm: float | Float[ArrayLike, ""] = 0.1,
    max_diameter_mm: float | Float[ArrayLike, ""] = P_MAX_MM,
) -> Float[Array, "*shape"]:
    """Pupil diameter under the hippus, eq. 1: ``p + A noise(t / p) (p_max / p) sqrt(1 - p/p_max)``.

    **Arguments:**

    - `t_s`: time (s).
    - `mean_diameter_mm`: the mean diameter `p` (mm), e.g. from
      :func:`moon_spencer_diameter_mm`; ``0 < p < p_max``.
    - `key`: `jax.random` key of the noise.
    - `amplitude_mm`: `A`, the scale of the three-octave value noise (mm, >= 0); see
      :func:`max_hippus_amplitude_mm` for the bound that keeps ``0 < h < p_max``.
    - `max_diameter_mm`: `p_max` (mm), 9 in the paper.

    **Returns:** the diameter (mm), same shape as `t_s` broadcast with `p`.

    **Example:**

    ```python
    h = hippus_diameter_mm(jnp.linspace(0, 10, 300), 2.5, jax.random.key(1))
    ```
    """
    p = as_float(mean_diameter_mm)
    noise = value_noise(as_float(t_s) / p, key)
    return p + amplitude_mm * noise * hippus_scale(p, max_diameter_mm)


def max_hippus_amplitude_mm(
    min_mean_mm: float, max_mean_mm: float, max_diameter_mm: float = P_MAX_MM
) -> float:
    """Largest amplitude `A` keeping eq. 1 inside ``(0, p_max)`` for means in a range.

    The noise is bounded by 1, so ``h`` stays positive while
    ``A < p**2 / (p_max sqrt(1 - p/p_max))`` and below `p_max` while
    ``A < p sqrt(1 - p/p_max)``; both are checked over ``[min_mean_mm, max_mean_mm]``
    (concrete floats). For the range of eq. 2 (1.9-7.9 mm) the bound is about 0.45 mm.
    """
    ps = np.linspace(min_mean_mm, max_mean_mm, 2001)
    q = ps / max_diameter_mm
    root = np.sqrt(np.maximum(1.0 - q, 1e-300))
    return float(min(np.min(ps * ps / (max_diameter_mm * root)), np.min(ps * root)))


def damp_luminance(
    previous_cd_m2: Float[ArrayLike, ""],
    current_cd_m2: Float[ArrayLike, ""],
    dt_s: float | Float[ArrayLike, ""],
    time_constant_s: float | Float[ArrayLike, ""],
) -> Float[Array, ""]:
    """One step of the time-damped field luminance: an exponential moving average.

    ``L <- L + (1 - exp(-dt / tau)) (L_frame - L)``: after a step change the average
    approaches the new level as ``1 - exp(-t / tau)`` whatever the frame rate.
    """
    alpha = -jnp.expm1(-as_float(dt_s) / time_constant_s)
    prev = as_float(previous_cd_m2)
    return prev + alpha * (as_float(current_cd_m2) - prev)


class PupilDynamics(eqx.Module):
    """Parameters of the pupil's motion (eq. 1 and 2).

    **Arguments:**

    - `hippus_amplitude_mm`: scale `A` of the hippus noise (mm, >= 0; 0 freezes the
      hippus). It must stay below :func:`max_hippus_amplitude_mm` over eq. 2's range
      (about 0.45 mm) so that the diameter stays within ``(0, p_max)``.
    - `max_diameter_mm`: `p_max` of eq. 1 (mm, > 7.9, the dark limit of eq. 2); 9.
    - `adaptation_time_s`: time constant (s, > 0) of the damped field luminance.
    - `from_luminance`: static; True: the mean diameter follows eq. 2 from the damped
      field luminance; False: it is the eye's own (rest) pupil diameter (a parameter to
      fit, and what "frozen" dynamics use).
    """

    hippus_amplitude_mm: Float[Array, ""] = eqx.field(converter=as_float, default=0.1)
    max_diameter_mm: Float[Array, ""] = eqx.field(converter=as_float, default=P_MAX_MM)
    adaptation_time_s: Float[Array, ""] = eqx.field(converter=as_float, default=0.5)
    from_luminance: bool = eqx.field(static=True, default=True)

    def __check_init__(self):
        check_range("pupil max_diameter_mm", self.max_diameter_mm, 7.9, lo_open=True, unit="mm")
        check_range("pupil adaptation_time_s", self.adaptation_time_s, 0.0, lo_open=True, unit="s")
        if is_concrete(self.max_diameter_mm):
            bound = max_hippus_amplitude_mm(*MOON_SPENCER_RANGE_MM, float(self.max_diameter_mm))
            check_range(
                "pupil hippus_amplitude_mm", self.hippus_amplitude_mm, 0.0, bound, unit="mm"
            )

    def mean_diameter_mm(
        self, field_luminance_cd_m2: Float[ArrayLike, ""], rest_diameter_mm: Float[ArrayLike, ""]
    ) -> Float[Array, ""]:
        """Eq. 2 of the field luminance, or the rest diameter when not `from_luminance`."""
        if self.from_luminance:
            return moon_spencer_diameter_mm(field_luminance_cd_m2)
        return as_float(rest_diameter_mm)

    def diameter_mm(
        self, t_s: Float[ArrayLike, ""], mean_mm: Float[ArrayLike, ""], key: Key[Array, ""]
    ) -> Float[Array, ""]:
        """The diameter at time `t_s` about `mean_mm`, eq. 1."""
        return hippus_diameter_mm(t_s, mean_mm, key, self.hippus_amplitude_mm, self.max_diameter_mm)
