"""Accommodation micro-fluctuations: the signal that squeezes the lens.

While the eye fixates a still target its accommodation keeps fluctuating by a few
tenths of a dioptre (Gray, Winn and Gilmartin 1993). The power spectrum has two
components, which Ritschel et al. (2009, sec. 3.3) reproduce:

- a **low-frequency** component below 0.6 Hz whose power grows with the pupil
  diameter: three-octave value noise (lattice rates `low_rate_hz`, twice and four
  times that), scaled by ``low_d_per_mm * pupil_mm``;
- a **narrow high-frequency** component between 1.3 and 2.1 Hz: in each eye a narrow
  peak of the spectrum somewhere in that range (Gray et al. find it at 1-2 Hz, its
  frequency varying from subject to subject): `n_high` cosines of random phases and
  frequencies within `high_width_hz` about `high_peak_hz` (which must lie in 1.3-2.1 Hz),
  of total RMS `high_rms_d`.

**Where the numbers come from.** The two bands, the low band's growth with the pupil
and its three octaves of value noise are the paper's (after Gray et al. 1993). The
amplitudes and rates are chosen values that put the components in those bands with
fluctuations of a few hundredths of a dioptre (Gray et al. report RMS fluctuations of
about 0.1 D in all): ``low_d_per_mm = 0.03`` D/mm, ``low_rate_hz = 0.08`` Hz,
``high_rms_d = 0.05`` D, ``high_peak_hz = 1.7`` Hz (the band's middle),
``high_width_hz = 0.1`` Hz and ``n_high = 8``.

The signal (dioptres, about 0) is a pure function of ``(t, key, pupil)``; it drives
the lens deformation of :mod:`invglare.dynamics.lens`.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Key

from invglare._core.checks import as_float, check_range, is_concrete
from invglare.dynamics.noise import uniform, value_noise
from invglare.errors import ConfigError, PhysicsRangeError

#: The range (Hz) of the high-frequency component's peak (Ritschel et al., after Gray et
#: al. 1993).
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
    - `high_peak_hz`: the centre of its narrow peak (Hz, within 1.3-2.1; a parameter).
    - `high_width_hz`: the peak's full width (Hz, > 0, at most 0.4): its cosines'
      frequencies are uniform in ``high_peak_hz +- high_width_hz / 2``, kept inside the
      1.3-2.1 Hz band.
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
    high_peak_hz: Float[Array, ""] = eqx.field(converter=as_float, default=1.7)
    high_width_hz: Float[Array, ""] = eqx.field(converter=as_float, default=0.1)
    n_high: int = eqx.field(static=True, default=8)

    def __check_init__(self):
        check_range("accommodation low_d_per_mm", self.low_d_per_mm, 0.0, unit="D/mm")
        check_range(
            "accommodation low_rate_hz", self.low_rate_hz, 0.0, 0.3, lo_open=True, unit="Hz"
        )
        check_range("accommodation high_rms_d", self.high_rms_d, 0.0, unit="D")
        lo, hi = HIGH_BAND_HZ
        check_range("accommodation high_peak_hz", self.high_peak_hz, lo, hi, unit="Hz")
        check_range(
            "accommodation high_width_hz", self.high_width_hz, 0.0, 0.4, lo_open=True, unit="Hz"
        )
        if is_concrete(self.high_peak_hz) and is_concrete(self.high_width_hz):
            peak, width = float(self.high_peak_hz), float(self.high_width_hz)
            if peak - 0.5 * width < lo - 1e-9 or peak + 0.5 * width > hi + 1e-9:
                raise PhysicsRangeError(
                    f"accommodation high-frequency peak {peak:g} +- {0.5 * width:g} Hz leaves "
                    f"the paper's {lo:g}-{hi:g} Hz band; move high_peak_hz or narrow "
                    "high_width_hz"
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
        offsets = uniform(k_f, (self.n_high,), t.dtype, -0.5, 0.5)
        freqs = self.high_peak_hz + self.high_width_hz * offsets
        phases = uniform(k_p, (self.n_high,), t.dtype, 0.0, 2.0 * math.pi)
        waves = jnp.cos(2.0 * math.pi * freqs * t[..., None] + phases)
        # sqrt(2 / n): each unit cosine has power 1/2, so the sum has RMS high_rms_d.
        return self.high_rms_d * math.sqrt(2.0 / self.n_high) * jnp.sum(waves, axis=-1)

    def signal_d(
        self, t_s: Float[ArrayLike, "*shape"], key: Key[Array, ""], pupil_mm: Float[ArrayLike, ""]
    ) -> Float[Array, "*shape"]:
        """Accommodation fluctuation (D) at times `t_s` for a pupil of `pupil_mm`."""
        return self.low_d(t_s, key, pupil_mm) + self.high_d(t_s, key)
