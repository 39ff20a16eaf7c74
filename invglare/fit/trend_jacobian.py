"""The derivative of a statistic of random draws: the trend, by central differences.

A model drawn from a fixed key (common random numbers) makes a statistic of its random
structure (the radial profile of a speckle, the angular energy of lashes) a jagged
function of the parameters: the exact derivative with respect to a relaxed count is that
of the one element fading in, and its interference with all the others swamps the
trend; a lash that crosses the pupil's edge as the row's spacing changes adds a step.
A least-squares solver then stalls or stops early, and a covariance from that derivative
measures the jaggedness, not how the statistic follows the parameter.

So a fit of statistics of unresolved draws (views with ``draws``, see
:mod:`invglare.fit.draw_scatter`) differentiates its residuals by central differences
over :data:`TREND_STEP` latent units (a few per cent of a bounded parameter's range;
:data:`COUNT_STEP` elements of a relaxed count): the slope of the trend.
:func:`trend_residuals` does that through a `jax.custom_jvp` whose rule evaluates only
the columns asked for (a solver's Jacobian, column by column, costs two evaluations per
parameter, as a JVP does). The invglare CIE study found the same (its ``FD_STEP``).

**Example:** ``dataclasses.replace(fn, trend_step=trend_steps(fn.space))`` makes a
residual function differentiate this way (``make_residual_fn`` does it for views with
draws).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero
from jaxtyping import Array, Float

#: Step (latent units) of the central differences: +-0.1 is about +-2.5 % of a logit
#: parameter's range at its middle, +-10 % of a log parameter.
TREND_STEP = 0.1
#: A relaxed count (a path ending in ``.count``) steps by this many elements either side
#: (at its initial value; the latent step is capped at 1): one element fading in is the
#: jaggedness itself, a trend needs a few.
COUNT_STEP = 2.0


def trend_steps(space: Any) -> tuple[float, ...]:
    """The latent step of each parameter of `space` (:data:`TREND_STEP`, or for a relaxed
    count the step of :data:`COUNT_STEP` elements at its initial value)."""
    steps = []
    for p in space.all:
        h = TREND_STEP
        if p.path.endswith(".count"):
            slope = float(p.dx_dz(p.to_latent(jnp.asarray(p.init))))
            h = min(max(COUNT_STEP / slope, TREND_STEP), 1.0) if slope > 0 else TREND_STEP
        steps.append(h)
    return tuple(steps)


@jax.custom_jvp
def _trend(fn: Any, *parts: Array) -> Array:
    return fn.exact_at_parts(list(parts))


def _trend_jvp(primals, tangents):
    fn, *parts = primals
    _, *t_parts = tangents
    value = fn.exact_at_parts(list(parts))
    out = jnp.zeros_like(value)
    for i, t in enumerate(t_parts):
        if isinstance(t, SymbolicZero):
            continue
        h = fn.trend_step[i]
        up = fn.exact_at_parts([*parts[:i], parts[i] + h, *parts[i + 1 :]])
        down = fn.exact_at_parts([*parts[:i], parts[i] - h, *parts[i + 1 :]])
        out = out + (up - down) / (2.0 * h) * t
    return value, out


_trend.defjvp(_trend_jvp, symbolic_zeros=True)


def trend_residuals(fn: Any, parts: Sequence[Array]) -> Float[Array, " n"]:
    """`fn`'s residuals at the latent values `parts`, differentiated by central differences
    over ``fn.trend_step[i]`` latent units in part `i` (module docstring); the values are
    exact."""
    return _trend(fn, *parts)
