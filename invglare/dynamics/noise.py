"""One-dimensional value noise: the random drive of the hippus and of accommodation.

Ritschel et al. (2009, sec. 3.2-3.3) drive the pupillary hippus and the slow part of the
accommodation micro-fluctuations with "value noise with three octaves" (Ebert et al.,
*Texturing & Modeling*). An octave is a lattice of random values, one per integer,
joined by a smooth cubic; octave `o` runs `2**o` times faster than the first and counts
`persistence**o` as much. The sum is divided by the sum of the octave weights, so the
noise stays within ``[-1, 1]``.

Lattice values come from ``fold_in(key, i)``: the noise is a pure function of
``(t, key)``, evaluated at any time without state, under `jit`, `vmap` and `grad`
(it is C1 in `t`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Key

from invglare.errors import ConfigError

# fold_in tag of octave `o` (offset so that octaves never share lattices with other users of
# the same key).
_OCTAVE_TAG = 7919


def uniform(key: Key[Array, ""], shape: tuple[int, ...], dtype, minval=0.0, maxval=1.0) -> Array:
    """Uniform draws made in float32 and cast to `dtype`.

    JAX draws other numbers for the same key in float64 than in float32; drawing in
    float32 always keeps a model's random structure (particles, lashes, saccades) the
    same whether it runs in float32 (a render) or float64 (a fit).
    """
    return jax.random.uniform(key, shape, jnp.float32, minval, maxval).astype(dtype)


def normal(key: Key[Array, ""], shape: tuple[int, ...], dtype) -> Array:
    """Standard-normal draws made in float32 and cast to `dtype` (see :func:`uniform`)."""
    return jax.random.normal(key, shape, jnp.float32).astype(dtype)


def _lattice(key: Key[Array, ""], index: Array, dtype) -> Array:
    """Uniform(-1, 1) value at each integer lattice point `index` (any shape)."""

    def one(i):
        # uint32 so that negative times wrap to distinct, reproducible lattice points.
        return uniform(jax.random.fold_in(key, i.astype(jnp.uint32)), (), dtype, -1.0, 1.0)

    flat = index.reshape(-1)
    return jax.vmap(one)(flat).reshape(index.shape)


def _smooth(u: Array) -> Array:
    """The cubic ``3 u**2 - 2 u**3``: C1 joins between lattice points."""
    return u * u * (3.0 - 2.0 * u)


def value_noise(
    t: Float[ArrayLike, "*shape"],
    key: Key[Array, ""],
    octaves: int = 3,
    persistence: float = 0.5,
) -> Float[Array, "*shape"]:
    """Multi-octave value noise in ``[-1, 1]`` at (dimensionless) times `t`.

    **Arguments:**

    - `t`: where to evaluate; one lattice step of the first octave per unit.
    - `key`: `jax.random` key of the lattices.
    - `octaves`: number of octaves (static, >= 1); the paper uses 3.
    - `persistence`: weight ratio of successive octaves (static, in ``(0, 1]``).

    **Returns:** the noise, same shape as `t`, in the float dtype of `t`.

    **Example:**

    ```python
    n = value_noise(jnp.linspace(0.0, 10.0, 500), jax.random.key(0))  # |n| <= 1
    ```
    """
    if not isinstance(octaves, int) or isinstance(octaves, bool) or octaves < 1:
        raise ConfigError(f"value noise octaves must be an integer >= 1, got {octaves!r}")
    if not 0.0 < float(persistence) <= 1.0:
        raise ConfigError(f"value noise persistence must be in (0, 1], got {persistence!r}")
    t = jnp.asarray(t)
    if not jnp.issubdtype(t.dtype, jnp.floating):
        t = t.astype(jnp.result_type(float))
    total = jnp.zeros_like(t)
    norm = 0.0
    for o in range(octaves):
        weight = float(persistence) ** o
        s = t * (2.0**o)
        i0 = jnp.floor(s)
        # floor carries no gradient; d/dt flows through the fractional part.
        u = _smooth(s - i0)
        k = jax.random.fold_in(key, _OCTAVE_TAG + o)
        i0 = i0.astype(jnp.int32)
        v0 = _lattice(k, i0, t.dtype)
        v1 = _lattice(k, i0 + 1, t.dtype)
        total = total + weight * (v0 + u * (v1 - v0))
        norm += weight
    return total / norm
