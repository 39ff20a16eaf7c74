"""Elementwise functions with finite gradients where the plain ones have none."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array


def safe_sqrt(x: Array) -> Array:
    """``sqrt(max(x, 0))`` with a finite (zero) gradient where ``x <= 0``.

    sqrt has an infinite slope at 0; the inner `where` keeps that NaN out of the gradient
    of the branch that is not taken.
    """
    positive = x > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), 0.0)
