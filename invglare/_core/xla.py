"""Helpers that steer XLA's code generation without changing any value."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Inexact


def materialise(x: Inexact[Array, "*shape"]) -> Inexact[Array, "*shape"]:
    """`x` itself, computed into memory before a pad or a scatter reads it.

    XLA's CPU backend fuses an elementwise producer into the pad that feeds an FFT (or
    into a scatter's updates) and then evaluates it element by element, unvectorised:
    a 256² disk raster padded to 512² took four times as long as the raster alone
    (`invglare bench`, case `psf_mono`), and the eyelash stamps of the daylight eye
    twice as long as materialised. A conditional on a runtime predicate is a
    fusion boundary; this one is never true (nothing exceeds +inf), so its other
    branch never runs. Under `vmap` the predicate is batched, the conditional
    becomes a select and the boundary is lost, with the same result.
    """
    first = jnp.real(x[(0,) * x.ndim])
    return jax.lax.cond(first > jnp.inf, jnp.zeros_like, lambda v: v, x)
