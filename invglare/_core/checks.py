"""Checks and conversions shared by every tier.

Values that may be traced (inside `jit`, `vmap` or `grad`) are checked only when they are
concrete: validation happens at the public boundary, where values still are.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Key

from invglare.errors import ConfigError, PhysicsRangeError


def is_concrete(x) -> bool:
    """Whether `x` holds values now (not a tracer of `jit`, `vmap` or `grad`)."""
    return not isinstance(x, jax.core.Tracer)


def as_float(x: ArrayLike) -> Array:
    """`jnp.asarray`, promoting Python numbers and integers to the default float dtype."""
    arr = jnp.asarray(x)
    if not jnp.issubdtype(arr.dtype, jnp.floating):
        arr = arr.astype(jnp.result_type(float))
    return arr


def shown(arr: ArrayLike) -> str:
    """A value for an error message: a scalar with ``%g``, an array abbreviated."""
    arr = np.asarray(arr)
    return f"{arr.item():g}" if arr.size == 1 else np.array2string(arr, precision=4)


def choose(name: str, value: str, valid: Sequence[str]) -> str:
    """Return `value` if it is one of `valid`, else raise a ConfigError listing them."""
    if value not in valid:
        raise ConfigError(f"{name} = {value!r} is not one of {', '.join(valid)}")
    return value


def check_static_int(name: str, value, lo: int) -> int:
    """`value` as an ``int``, or a :class:`ConfigError` unless it is a Python (or NumPy)
    integer >= `lo` (not a bool)."""
    if not isinstance(value, int | np.integer) or isinstance(value, bool) or value < lo:
        raise ConfigError(f"{name} must be an integer >= {lo}, got {value!r}")
    return int(value)


def check_positive(name: str, value, unit: str = "") -> None:
    """Raise :class:`PhysicsRangeError` unless every element of a concrete `value` is > 0."""
    if not is_concrete(value):
        return
    arr = np.asarray(value, dtype=float)
    if arr.size == 0 or not np.all(np.isfinite(arr)) or np.any(arr <= 0):
        suffix = f" {unit}" if unit else ""
        raise PhysicsRangeError(f"{name} must be finite and > 0, got {shown(arr)}{suffix}")


def check_range(
    name: str,
    value,
    lo: float,
    hi: float = math.inf,
    *,
    lo_open: bool = False,
    hi_open: bool = False,
    unit: str = "",
) -> None:
    """Raise :class:`PhysicsRangeError` unless a concrete `value` is finite and within bounds."""
    if not is_concrete(value):
        return
    arr = np.asarray(value, dtype=float)
    bad = ~np.isfinite(arr)
    bad |= (arr <= lo) if lo_open else (arr < lo)
    bad |= (arr >= hi) if hi_open else (arr > hi)
    if np.any(bad):
        lo_txt = f"> {lo:g}" if lo_open else f">= {lo:g}"
        hi_txt = "" if math.isinf(hi) else (f" and < {hi:g}" if hi_open else f" and <= {hi:g}")
        suffix = f" {unit}" if unit else ""
        raise PhysicsRangeError(
            f"{name} must be finite, {lo_txt}{hi_txt}, got {shown(arr)}{suffix}"
        )


def as_key(x) -> Key[Array, ""]:
    """A typed PRNG key from a typed key, raw key data (``uint32[2]``) or an integer seed."""
    if isinstance(x, int | np.integer) and not isinstance(x, bool):
        return jax.random.key(int(x))
    try:
        arr = None if isinstance(x, str) else jnp.asarray(x)
    except TypeError:
        arr = None
    if arr is None:
        raise ConfigError(
            f"a random key must be a jax.random.key, raw uint32 key data or an int seed, got {x!r}"
        )
    if jnp.issubdtype(arr.dtype, jax.dtypes.prng_key):
        return arr
    if arr.dtype == jnp.uint32:
        return jax.random.wrap_key_data(arr)
    raise ConfigError(
        f"a random key must be a jax.random.key, raw uint32 key data or an int seed, "
        f"got {type(x).__name__} of dtype {arr.dtype}"
    )
