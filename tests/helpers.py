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


def assert_fd_converges(
    f: Callable, x: float, ad: float, eps: float, rtol: float = 1e-5, atol: float = 0.0
) -> tuple[float, float]:
    """Assert that central differences of `f` at `x` converge to the derivative `ad`.

    The differences are taken at two steps, `eps` and `eps / 2` (run under `x64()`). A
    right derivative passes both checks: the finer difference agrees with `ad` to `rtol`,
    and halving the step at least halves the discrepancy (truncation error falls as
    ``eps**2``, four times per halving) unless both are down at the floor of rounding. A
    wrong derivative keeps its discrepancy as the step shrinks.

    The floor is `atol` plus the rounding of the fine difference, ``8 * (float64
    epsilon) * |f(x)| / (eps / 2)`` (a few units in the last place of `f`, divided by the
    step). Choose `eps` so that truncation, not rounding, dominates where the function
    is smooth (about 1e-5 to 1e-4 of the parameter's scale).

    Returns the two differences (coarse, fine).
    """
    coarse = central_difference(f, x, eps)
    fine = central_difference(f, x, eps / 2)
    rounding = 8.0 * np.finfo(np.float64).eps * abs(float(f(jnp.float64(x)))) / (eps / 2)
    floor = atol + rounding
    np.testing.assert_allclose(ad, fine, rtol=rtol, atol=floor)
    err_coarse, err_fine = abs(coarse - ad), abs(fine - ad)
    assert err_fine <= 0.5 * err_coarse + floor, (
        f"central differences do not converge to {ad!r}: {coarse!r} at step {eps:g}, "
        f"{fine!r} at {eps / 2:g} (rounding floor {floor:.2g})"
    )
    return coarse, fine


def assert_grad_converges(
    f: Callable, x: float, eps: float, rtol: float = 1e-5, atol: float = 0.0
) -> tuple[float, float, float]:
    """Autodiff ``d f/dx`` checked by :func:`assert_fd_converges`.

    Returns (autodiff, coarse difference, fine difference).
    """
    ad = float(jax.grad(f)(jnp.float64(x)))
    return (ad, *assert_fd_converges(f, x, ad, eps, rtol, atol))
