"""Shared test utilities: float64 context and finite-difference gradient checks."""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np


def x64():
    """Context manager enabling float64 for a gradient or precision test."""
    return jax.enable_x64(True)


def central_difference(f: Callable, x: float, eps: float = 1e-6) -> float:
    """Central finite difference of a scalar function of one scalar (run under `x64()`)."""
    return float((f(jnp.float64(x + eps)) - f(jnp.float64(x - eps))) / (2 * eps))


def assert_grad_matches_fd(
    f: Callable, x: float, eps: float = 1e-6, rtol: float = 1e-5, atol: float = 1e-10
) -> tuple[float, float]:
    """Assert autodiff d f/dx equals the central difference; returns (autodiff, fd)."""
    ad = float(jax.grad(f)(jnp.float64(x)))
    fd = central_difference(f, x, eps)
    np.testing.assert_allclose(ad, fd, rtol=rtol, atol=atol)
    return ad, fd
