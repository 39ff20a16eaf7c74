"""The pool of a relaxed count, its random draws, and the stamp window of its elements.

**Relaxed counts.** Lashes, particles and gratings are drawn as a fixed pool of
`n_max` elements from an explicit `jax.random` key; element `i` is weighted by
``smooth_step(count - i)`` (a cubic step from 0 at ``count = i`` to 1 at
``count = i + 1``). At an integer count exactly that many elements are present;
in between, one element fades in. Element `i`'s random numbers come from
``fold_in(key, i)``, so they do not depend on `n_max`: growing the pool keeps
the existing elements. The draws are *unit* random numbers (uniform or standard
normal) scaled by the parameters, so gradients reach spreads, lengths and sizes.
The derivative with respect to a count is 0 at exact integers (the step is
flat at both ends); start a fit at a non-integer count.

**Stamp windows.** Each element is rasterised on a small local window
(:mod:`invglare.aperture.shapes.stamps`) whose half-size is a static shape: computed
here from concrete parameters and the grid pitch, or fixed beforehand with
:meth:`~invglare.aperture.eye.EyeAperture.with_stamp_windows`.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Key

from invglare._core.checks import as_float, check_range
from invglare._core.grids import ApertureGrid
from invglare.aperture.shapes.stamps import window_half_px
from invglare.dynamics.noise import normal, uniform
from invglare.errors import ConfigError, PhysicsRangeError


def check_n_max(owner: str, n_max) -> None:
    """Raise unless the pool size `n_max` is a static integer >= 1."""
    if not isinstance(n_max, int | np.integer) or isinstance(n_max, bool):
        raise ConfigError(f"{owner} n_max must be an integer (static pool size), got {n_max!r}")
    if n_max < 1:
        raise PhysicsRangeError(f"{owner} n_max must be >= 1, got {n_max}")


def check_count(owner: str, count, n_max: int) -> None:
    """Raise :class:`PhysicsRangeError` unless a concrete `count` lies in ``[0, n_max]``."""
    check_range(f"{owner} count", count, 0.0, float(n_max))


def smooth_step(t: Float[ArrayLike, "*shape"]) -> Float[Array, "*shape"]:
    """Cubic step ``3 t**2 - 2 t**3`` on ``[0, 1]``, 0 below and 1 above; C1 everywhere."""
    t = jnp.clip(jnp.asarray(t), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def relaxed_weights(count: Float[ArrayLike, ""], n_max: int) -> Float[Array, " n_max"]:
    """Weights ``smooth_step(count - i)`` of the pool elements ``i = 0 .. n_max - 1``.

    At an integer `count` = k the first k weights are 1 and the rest 0.
    """
    count = as_float(count)
    return smooth_step(count - jnp.arange(n_max, dtype=count.dtype))


def unit_draws(
    key: Key[Array, ""], n: int, n_uniform: int, n_normal: int, dtype
) -> tuple[Float[Array, "n u"], Float[Array, "n g"]]:
    """Per-element uniform(0, 1) and standard-normal draws, element `i` from ``fold_in(key, i)``.

    Drawing per element (rather than one array of `n` draws) makes element `i`'s
    numbers independent of `n`, so pools of different `n_max` share their elements.
    """

    def one(i):
        k_u, k_n = jax.random.split(jax.random.fold_in(key, i))
        return (
            uniform(k_u, (n_uniform,), dtype),
            normal(k_n, (n_normal,), dtype),
        )

    return jax.vmap(one)(jnp.arange(n))


def dtype_of(*values) -> Any:
    """The float dtype of the draws for parameters `values` (float32 unless one is wider)."""
    return jnp.result_type(*values, float)


@eqx.filter_jit
def stamp_bound(component) -> Array:
    """``component.stamp_bound()``: the largest half-extent (mm) of one of its elements."""
    # jitted: evaluated eagerly, the few dozen small operations would each be compiled.
    return component.stamp_bound()


def stamp_window(owner: str, grid: ApertureGrid, component) -> int:
    """The window half-size (px) of a stamped component (see the module docstring)."""
    if component.stamp_half_px is not None:
        return int(component.stamp_half_px)
    bound = component.stamp_bound_mm
    if bound is None:
        bound = stamp_bound(component)
    try:
        return window_half_px(bound, grid.pitch_mm)
    except ConfigError as err:
        raise ConfigError(f"{owner}: {err}") from err
