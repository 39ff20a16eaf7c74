"""The Poisson–Gaussian likelihood of a photo as least-squares residuals (deviance residuals).

Per unclipped pixel the likelihood is the one :meth:`Observation.log_likelihood
<invglare.fit.Observation.log_likelihood>` gives and `invglare sample` samples: observed
counts `o` given the unclipped mean `mu` are normal with the Poisson–Gaussian variance
``V(mu) = max(mu, 0) / gain + read_noise**2``,

```
l(mu) = -((o - mu)**2 / V(mu) + log(2 pi V(mu))) / 2.
```

Its largest value over `mu`, ``l* = l(mu*)``, depends on the data only, so the *deviance
residual*

```
r = sign(mu* - mu) * sqrt(2 (l* - l(mu)))
```

has ``sum(r**2) / 2 = sum(l*) - log L``: minimising the sum of squares *is* maximising
the likelihood, and ``d/dtheta sum(r**2) / 2 = -d log L / dtheta`` exactly, for every
parameter the noise model's gain and read noise do not depend on (``l*`` does). A clipped
pixel's censored term ``log Phi((mu - S) / sqrt(V))`` has its largest value 0, so its
residual is ``sqrt(-2 log Phi)``, as before.

`mu*` is in closed form: on ``mu > 0``, ``dl/dmu = 0`` is a quadratic in ``d = o - mu``,
``d**2 - (1/g + 2 o + 2 g s**2) d + (o / g + s**2) = 0``, whose smaller root is the maximum
(``d`` is about ``1 / (2 g)``: the likelihood's own peak sits a little below `o`, because a
smaller mean has a smaller variance). A negative `o` peaks at ``mu* = o`` (constant variance
there); a small positive `o` whose root falls below 0 peaks at the kink, ``mu* = 0``.

Near the peak ``l* - l(mu)`` is a difference of nearly equal numbers; with ``delta = mu -
mu*``, ``V* = V(mu*)`` and ``u = delta / (g V*)`` it is, exactly (both on ``mu > 0``),

```
2 (l* - l) = delta**2 / V(mu) + log1p(u) - u / (1 + u),
```

two non-negative terms, so ``r = -delta sqrt(1 / V + q(u) / (g V*)**2)`` with ``q(u) =
(log1p(u) - u / (1 + u)) / u**2`` (by its series for small `u`) is smooth through the peak.

**Information.** The covariance of a fit is the inverse Fisher information of this
likelihood: per pixel ``w = 1 / V + V'**2 / (2 V**2)`` (``V' = 1 / gain`` above 0 counts)
times the outer product of the mean's gradient (:func:`fisher_weight`).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from invglare._core.maths import safe_sqrt

# Variances are floored here: a pixel with no read noise and no light has none, and the
# Gaussian likelihood is then degenerate (the fit refuses such photos; see
# `invglare.fit.views.check_likelihood_input`).
_TINY = 1e-30


def _variance(mean: Array, gain: Array, read_noise: Array) -> Array:
    return jnp.maximum(jnp.maximum(mean, 0.0) / gain + read_noise**2, _TINY)


def likelihood_peak(
    observed: Float[ArrayLike, "*shape"], gain: ArrayLike, read_noise: ArrayLike
) -> tuple[Float[Array, "*shape"], Float[Array, "*shape"]]:
    """``(mu*, V(mu*))``: the mean that maximises each pixel's likelihood, and its variance.

    `gain` in electrons per count, `read_noise` in counts (module docstring).
    """
    o = jnp.asarray(observed)
    g = jnp.asarray(gain, o.dtype)
    s2 = jnp.asarray(read_noise, o.dtype) ** 2
    b = 1.0 / g + 2.0 * o + 2.0 * g * s2
    c = o / g + s2
    # The smaller root in the form that keeps its digits (b > 0 wherever o >= 0); the
    # discriminant b**2 - 4 c = 1 / g**2 + (2 o + 2 g s**2)**2 is positive.
    disc = jnp.sqrt((1.0 / g) ** 2 + (2.0 * o + 2.0 * g * s2) ** 2)
    d = 2.0 * c / jnp.where(o >= 0, b + disc, 1.0)
    mu = jnp.where(o < 0, o, jnp.maximum(o - d, 0.0))
    return mu, _variance(mu, g, jnp.sqrt(s2))


def _q(u: Array) -> Array:
    """``(log1p(u) - u / (1 + u)) / u**2`` for ``u > -1``; its series below ``|u| = 0.1``."""
    small = jnp.abs(u) < 0.1
    us = jnp.where(small, u, 0.0)
    series = jnp.zeros_like(u)
    for k in range(11, -1, -1):  # sum_k (-1)^k (k + 1) / (k + 2) u^k, Horner
        series = series * us + (-1.0) ** k * (k + 1) / (k + 2)
    ul = jnp.where(small, 1.0, u)
    direct = (jnp.log1p(ul) - ul / (1.0 + ul)) / (ul * ul)
    return jnp.where(small, series, direct)


def deviance_residuals(
    observed: Float[ArrayLike, "*shape"],
    expected: Float[ArrayLike, "*shape"],
    gain: ArrayLike,
    read_noise: ArrayLike,
) -> Float[Array, "*shape"]:
    """``sign(mu* - mu) sqrt(2 (l* - l(mu)))`` per pixel (module docstring), unclipped pixels.

    Positive where the model is below the data, like ``o - mu``; about ``(o - mu) /
    sqrt(V)`` for many counts. Smooth in `expected` except where `mu*` or the mean sits at
    the variance's kink at 0 counts (the likelihood itself has a corner there).
    """
    o = jnp.asarray(observed)
    e = jnp.asarray(expected, o.dtype)
    g = jnp.asarray(gain, o.dtype)
    s = jnp.asarray(read_noise, o.dtype)
    mu_s, v_s = likelihood_peak(o, g, s)
    v = _variance(e, g, s)
    delta = e - mu_s
    # Both on the branch where V grows linearly (the usual case): the stable form.
    pos = (e > 0) & (mu_s > 0)
    u = jnp.where(pos, delta / (g * v_s), 0.0)
    core = 1.0 / v + _q(u) / (g * v_s) ** 2
    r_pos = -delta * jnp.sqrt(core)
    # A negative pixel and a mean at or below 0: constant variance, an ordinary residual.
    flat = (e <= 0) & (o < 0)
    r_flat = (o - e) / jnp.sqrt(v)
    # Elsewhere (one side of the kink or the other) the direct difference, away from 0
    # except at the kink itself.
    dev = (o - e) ** 2 / v + jnp.log(v) - (o - mu_s) ** 2 / v_s - jnp.log(v_s)
    r_gen = jnp.sign(mu_s - e) * safe_sqrt(dev)
    return jnp.where(pos, r_pos, jnp.where(flat, r_flat, r_gen))


def pixel_log_likelihood_gradient(
    observed: Float[ArrayLike, "*shape"],
    expected: Float[ArrayLike, "*shape"],
    gain: ArrayLike,
    read_noise: ArrayLike,
) -> Float[Array, "*shape"]:
    """``dl/dmu`` per unclipped pixel, the score of the likelihood in the mean (counts⁻¹)."""
    o = jnp.asarray(observed)
    e = jnp.asarray(expected, o.dtype)
    g = jnp.asarray(gain, o.dtype)
    v = _variance(e, g, jnp.asarray(read_noise, o.dtype))
    dv = jnp.where(e > 0, 1.0 / g, 0.0)
    d = o - e
    return d / v + (d * d / v - 1.0) * dv / (2.0 * v)


def fisher_weight(
    expected: Float[ArrayLike, "*shape"], gain: ArrayLike, read_noise: ArrayLike
) -> Float[Array, "*shape"]:
    """Fisher information of an unclipped pixel about its mean, ``1/V + V'**2 / (2 V**2)``."""
    e = jnp.asarray(expected)
    g = jnp.asarray(gain, e.dtype)
    v = _variance(e, g, jnp.asarray(read_noise, e.dtype))
    dv = jnp.where(e > 0, 1.0 / g, 0.0)
    return 1.0 / v + dv * dv / (2.0 * v * v)
