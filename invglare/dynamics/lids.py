"""Blinking and squinting: how far the lids are open over time.

Ritschel et al. (2009, sec. 3.6) animate blinks by moving the lids and lashes over the
pupil, and model squinting, a normal reaction to a discomforting glare source, as
lids held closed by a constant amount. Both are one number here, the **open
fraction** ``(1 - squint) (1 - closure(t))`` in ``[0, 1]``, by which the eye model
multiplies its rest lid openings (so the lashes, rooted on the margins, move with
them). At full closure both margins reach the axis and the aperture is shut.

**Blinks** start at ``first_blink_s + k interval_s`` shifted by
``jitter * interval_s * (u_k - 1/2)`` (``u_k`` uniform, from the key), close over
`close_s` (a cubic ease), stay shut for `hold_s` and reopen over `open_s` (real blinks
close in about 0.1 s and reopen more slowly). ``interval_s = 0`` means no blinking.

**Where the numbers come from.** The paper gives no blink timing. The defaults are
chosen values in the range of spontaneous blinks (15-20 a minute, hence 4 s apart;
closing in 80 ms, shut for 40 ms, reopening in 180 ms); ``squint = 0`` (no squint) is
chosen too: set it for an observer screwing up the eyes at a glare source.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Key

from invglare._core.checks import as_float, check_range
from invglare.dynamics.noise import _smooth, uniform
from invglare.errors import ConfigError

_BLINK_TAG = 31


class LidMotion(eqx.Module):
    """Parameters of blinking and squinting.

    **Arguments:**

    - `interval_s`: mean time between blinks (s, >= 0; 0: no blinks). About 4 s.
    - `jitter`: randomness of the blink times, a fraction of the interval in ``[0, 1)``.
    - `first_blink_s`: start of the first (unjittered) blink (s).
    - `close_s`, `hold_s`, `open_s`: durations (s) of closing, staying shut, reopening.
    - `squint`: fraction of the rest opening held closed, in ``[0, 1]``.

    **Example:**

    ```python
    lids = LidMotion(interval_s=4.0, jitter=0.0, first_blink_s=1.0)
    lids.open_fraction(lids.mid_blink_s(0), jax.random.key(0))  # 0.0: shut
    ```
    """

    interval_s: Float[Array, ""] = eqx.field(converter=as_float, default=4.0)
    jitter: Float[Array, ""] = eqx.field(converter=as_float, default=0.3)
    first_blink_s: Float[Array, ""] = eqx.field(converter=as_float, default=2.0)
    close_s: Float[Array, ""] = eqx.field(converter=as_float, default=0.08)
    hold_s: Float[Array, ""] = eqx.field(converter=as_float, default=0.04)
    open_s: Float[Array, ""] = eqx.field(converter=as_float, default=0.18)
    squint: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)

    def __check_init__(self):
        check_range("lids interval_s", self.interval_s, 0.0, unit="s")
        check_range("lids jitter", self.jitter, 0.0, 0.999)
        check_range("lids first_blink_s", self.first_blink_s, -np.inf, unit="s")
        check_range("lids close_s", self.close_s, 0.0, lo_open=True, unit="s")
        check_range("lids hold_s", self.hold_s, 0.0, unit="s")
        check_range("lids open_s", self.open_s, 0.0, lo_open=True, unit="s")
        check_range("lids squint", self.squint, 0.0, 1.0)
        values = (self.interval_s, self.jitter, self.close_s, self.hold_s, self.open_s)
        if all(not isinstance(v, jax.core.Tracer) for v in values):
            interval, jitter = float(self.interval_s), float(self.jitter)
            duration = float(self.close_s + self.hold_s + self.open_s)
            if interval > 0 and duration > interval * (1.0 - jitter):
                raise ConfigError(
                    f"a blink ({duration:g} s) must fit between blinks: interval_s * (1 - jitter) "
                    f"= {interval * (1.0 - jitter):g} s; lengthen interval_s or shorten the blink"
                )

    @property
    def blinks(self) -> bool:
        """Whether blinking is on (concrete parameters)."""
        return float(self.interval_s) > 0.0

    def blink_start_s(self, k: Array, key: Key[Array, ""]) -> Array:
        """Start time (s) of blink number `k` (an integer array)."""
        u = uniform(
            jax.random.fold_in(jax.random.fold_in(key, _BLINK_TAG), k.astype(jnp.uint32)),
            (),
            self.interval_s.dtype,
        )
        base = self.first_blink_s + k.astype(self.interval_s.dtype) * self.interval_s
        return base + self.jitter * self.interval_s * (u - 0.5)

    def mid_blink_s(self, k: int, key: Key[Array, ""]) -> Array:
        """The middle of blink `k`'s shut phase (s): the moment the aperture is closed."""
        start = self.blink_start_s(jnp.asarray(k, jnp.int32), key)
        return start + self.close_s + 0.5 * self.hold_s

    def _profile(self, tau: Array) -> Array:
        """Closure (0 open, 1 shut) at time `tau` since a blink started."""
        closing = _smooth(jnp.clip(tau / self.close_s, 0.0, 1.0))
        reopening = _smooth(jnp.clip((tau - self.close_s - self.hold_s) / self.open_s, 0.0, 1.0))
        return jnp.where(tau < 0.0, 0.0, closing - reopening)

    def closure(self, t_s: Float[ArrayLike, ""], key: Key[Array, ""]) -> Float[Array, ""]:
        """Blink closure in ``[0, 1]`` at time `t_s` (0 without blinking)."""
        t = as_float(t_s)
        interval = jnp.where(self.interval_s > 0, self.interval_s, 1.0)
        k = jnp.floor((t - self.first_blink_s) / interval).astype(jnp.int32)
        # Blinks are shorter than the gap between them, so the current one is k - 1, k or k + 1.
        ks = k + jnp.arange(-1, 2, dtype=jnp.int32)
        starts = jax.vmap(lambda kk: self.blink_start_s(kk, key))(ks)
        c = jnp.max(self._profile(t - starts))
        return jnp.where(self.interval_s > 0, c, 0.0)

    def open_fraction(self, t_s: Float[ArrayLike, ""], key: Key[Array, ""]) -> Float[Array, ""]:
        """``(1 - squint) (1 - closure(t))``: the lids' opening relative to rest."""
        return (1.0 - self.squint) * (1.0 - self.closure(t_s, key))
