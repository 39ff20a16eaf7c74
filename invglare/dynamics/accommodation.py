"""Accommodation micro-fluctuations: the signal that squeezes the lens.

While the eye fixates a still target its accommodation keeps fluctuating by a few
tenths of a dioptre (Gray, Winn and Gilmartin 1993). The power spectrum has two
components, which Ritschel et al. (2009, sec. 3.3) reproduce:

- a **low-frequency** component below 0.6 Hz whose power grows with the pupil
  diameter: three-octave value noise (lattice rates `low_rate_hz`, twice and four
  times that), scaled by ``low_d_per_mm * pupil_mm``;
- a **narrow high-frequency** component between 1.3 and 2.1 Hz: a sum of
  `n_high` cosines of random frequencies in that band and random phases, of total
  RMS `high_rms_d`.

The signal (dioptres, about 0) is a pure function of ``(t, key, pupil)``; it drives
the lens deformation of :mod:`invglare.dynamics.lens`.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Key

from invglare._core.checks import as_float, check_range
from invglare.dynamics.noise import uniform, value_noise
from invglare.errors import ConfigError, PhysicsRangeError

#: The band of the high-frequency component (Hz), after Gray et al. (1993).
HIGH_BAND_HZ = (1.3, 2.1)
#: Upper limit (Hz) of the low-frequency component.
LOW_BAND_MAX_HZ = 0.6

_LOW_TAG, _HIGH_TAG = 11, 12


class Accommodation(eqx.Module):
    """Parameters of the accommodation micro-fluctuations.

    **Arguments:**

    - `low_d_per_mm`: scale of the low-frequency component per mm of pupil diameter
      (D/mm, >= 0): the component is ``low_d_per_mm * pupil_mm * noise``, noise in
      ``[-1, 1]``, so its power grows as the pupil diameter squared.
    - `low_rate_hz`: lattice rate of the first noise octave (Hz, > 0; the others run
      at 2x and 4x). With the default 0.08 Hz about 99 % of the component's power lies
      below 0.6 Hz.
    - `high_rms_d`: RMS of the high-frequency component (D, >= 0).
    - `high_band_hz`: static (lo, hi) band of its frequencies (Hz), 1.3-2.1 by default.
    - `n_high`: static number of cosines in the high-frequency component.

    **Example:**

    ```python
    acc = Accommodation()
    a = acc.signal_d(jnp.linspace(0, 60, 1800), jax.random.key(0), 6.0)  # dioptres
    ```
    """

    low_d_per_mm: Float[Array, ""] = eqx.field(converter=as_float, default=0.03)
    low_rate_hz: Float[Array, ""] = eqx.field(converter=as_float, default=0.08)
    high_rms_d: Float[Array, ""] = eqx.field(converter=as_float, default=0.05)
    high_band_hz: tuple[float, float] = eqx.field(static=True, default=HIGH_BAND_HZ)
    n_high: int = eqx.field(static=True, default=8)

    def __check_init__(self):
        check_range("accommodation low_d_per_mm", self.low_d_per_mm, 0.0, unit="D/mm")
        check_range(
            "accommodation low_rate_hz", self.low_rate_hz, 0.0, 0.3, lo_open=True, unit="Hz"
        )
        check_range("accommodation high_rms_d", self.high_rms_d, 0.0, unit="D")
        lo, hi = self.high_band_hz
        if not (0.0 < lo < hi and math.isfinite(hi)):
            raise PhysicsRangeError(
                f"accommodation high_band_hz must be (lo, hi) with 0 < lo < hi, got "
                f"{self.high_band_hz}"
            )
        if not isinstance(self.n_high, int) or isinstance(self.n_high, bool) or self.n_high < 1:
            raise ConfigError(f"accommodation n_high must be an integer >= 1, got {self.n_high!r}")

    def low_d(
        self, t_s: Float[ArrayLike, "*shape"], key: Key[Array, ""], pupil_mm: Float[ArrayLike, ""]
    ) -> Float[Array, "*shape"]:
        """The low-frequency component (D)."""
        noise = value_noise(as_float(t_s) * self.low_rate_hz, jax.random.fold_in(key, _LOW_TAG))
        return self.low_d_per_mm * as_float(pupil_mm) * noise

    def high_d(
        self, t_s: Float[ArrayLike, "*shape"], key: Key[Array, ""]
    ) -> Float[Array, "*shape"]:
        """The narrow-band high-frequency component (D)."""
        t = as_float(t_s)
        k_f, k_p = jax.random.split(jax.random.fold_in(key, _HIGH_TAG))
        lo, hi = self.high_band_hz
        freqs = uniform(k_f, (self.n_high,), t.dtype, lo, hi)
        phases = uniform(k_p, (self.n_high,), t.dtype, 0.0, 2.0 * math.pi)
        waves = jnp.cos(2.0 * math.pi * freqs * t[..., None] + phases)
        # sqrt(2 / n): each unit cosine has power 1/2, so the sum has RMS high_rms_d.
        return self.high_rms_d * math.sqrt(2.0 / self.n_high) * jnp.sum(waves, axis=-1)

    def signal_d(
        self, t_s: Float[ArrayLike, "*shape"], key: Key[Array, ""], pupil_mm: Float[ArrayLike, ""]
    ) -> Float[Array, "*shape"]:
        """Accommodation fluctuation (D) at times `t_s` for a pupil of `pupil_mm`."""
        return self.low_d(t_s, key, pupil_mm) + self.high_d(t_s, key)
