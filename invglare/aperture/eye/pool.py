"""The relaxed-count pool shared by lashes, particles and gratings (see the package docstring).

:class:`AbstractPool` holds what every pool has (`count`, `n_max`, `key`) and what it does
alike: the weights ``smooth_step(count - i)`` of its elements, per-element unit draws from
``fold_in(key, i)``, and the static stamp window its elements are rasterised on.
"""

from __future__ import annotations

import abc
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Key

from invglare._core.checks import as_float, as_key, check_range
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


class AbstractPool(eqx.Module):
    """A pool of `n_max` elements of which the first `count` (relaxed) are present.

    **Fields** (the first three of every pool, in this order):

    - `count`: number of elements (float, relaxed; ``0 <= count <= n_max``).
    - `n_max`: size of the pool (static).
    - `key`: `jax.random` key of the elements' variations (a typed key, raw ``uint32``
      key data or an int seed; stored as a typed key).

    A final subclass adds its own parameters and, last, the static stamp-window
    overrides `stamp_bound_mm` and `stamp_half_px` (None: automatic), and says what one
    element claims (:meth:`stamp_bound`) and how it is named in messages (`owner`).
    """

    count: Float[Array, ""] = eqx.field(converter=as_float)
    n_max: int = eqx.field(static=True)
    key: Key[Array, ""] = eqx.field(converter=as_key)
    stamp_bound_mm: eqx.AbstractVar[float | None]
    stamp_half_px: eqx.AbstractVar[int | None]

    @property
    @abc.abstractmethod
    def owner(self) -> str:
        """How messages name the pool (e.g. ``"upper lashes"``)."""

    @abc.abstractmethod
    def stamp_bound(self) -> Float[Array, ""]:
        """Largest half-extent (mm) of the pixels one element claims."""

    def __check_init__(self):
        check_n_max(self.owner, self.n_max)
        check_count(self.owner, self.count, self.n_max)

    def weights(self) -> Float[Array, " n_max"]:
        """Relaxed-count weight of each element of the pool."""
        return relaxed_weights(self.count, self.n_max)

    def window_half_px(self, grid: ApertureGrid) -> int:
        """Static stamp-window half-size (px) of the pool's elements on `grid`."""
        return stamp_window(self.owner, grid, self)
