"""jinc and J1 of `invglare.optics.bessel` against scipy, in both precisions."""

import jax
import jax.numpy as jnp
import numpy as np
from helpers import x64
from scipy.special import j1, jv

from invglare.optics.bessel import bessel_j1, jinc


def _jinc_reference(x: np.ndarray) -> np.ndarray:
    safe = np.where(x == 0, 1.0, x)
    return np.where(x == 0, 1.0, 2.0 * j1(safe) / safe)


# Dense where the two pieces meet (x = 17) and where the veiling series needs them
# (up to ~2000), sparse out to 1e7 where the pi/2 reduction is exercised.
_ARGS = np.concatenate(
    [np.linspace(0.0, 60.0, 60001), np.geomspace(1e-6, 5e3, 4001), [1e5, 123456.7, 1e7 + 0.3]]
)


def test_jinc_float64_within_1e13_of_scipy():
    with x64():
        err = np.abs(np.asarray(jinc(_ARGS)) - _jinc_reference(_ARGS))
        assert err.max() < 1e-13  # measured 2.7e-15
        # J1 = x jinc / 2 scales the error with x: 1e-13 up to 3000, 1e-6 at 1e7.
        small = _ARGS < 3000
        np.testing.assert_allclose(bessel_j1(_ARGS[small]), j1(_ARGS[small]), rtol=0, atol=1e-13)
        np.testing.assert_allclose(bessel_j1(_ARGS), j1(_ARGS), rtol=0, atol=1e-6)


def test_jinc_float32_within_2e6_of_scipy():
    x = _ARGS[_ARGS < 5e3].astype(np.float32)
    value = jinc(x)
    assert value.dtype == jnp.float32
    # The reference at the float32 argument: the error is the method's, not the rounding of x.
    err = np.abs(np.asarray(value, np.float64) - _jinc_reference(x.astype(np.float64)))
    assert err.max() < 2e-6  # measured 9e-7


def test_jinc_gradient_is_the_bessel_derivative_across_the_switch():
    with x64():
        # d/dx [2 J1(x) / x] = -2 J2(x) / x; checked on both sides of x = 17 and at 0.
        x = np.concatenate([[0.0], np.linspace(15.0, 19.0, 401), [250.0, 2500.5]])
        grad = jax.vmap(jax.grad(lambda t: jinc(t)))(jnp.asarray(x))
        safe = np.where(x == 0, 1.0, x)
        expected = np.where(x == 0, 0.0, -2.0 * jv(2, safe) / safe)
        np.testing.assert_allclose(grad, expected, rtol=0, atol=1e-13)


def test_jinc_is_even_and_takes_integers_and_batches():
    with x64():
        np.testing.assert_allclose(jinc(jnp.array([-3.0, -30.0])), jinc(jnp.array([3.0, 30.0])))
        assert abs(float(jinc(0)) - 1.0) < 1e-15
        x = np.linspace(0.0, 40.0, 12).reshape(3, 4)
        np.testing.assert_allclose(jax.vmap(jinc)(x), _jinc_reference(x), atol=1e-13)
