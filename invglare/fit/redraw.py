"""Another eye of the same population: a model with its random keys drawn anew.

A model with random structure (a pool of lashes drawn from its key, cornea cells, lens
particles, fibre gratings, a camera's dust) holds typed `jax.random` keys among its
leaves. :func:`redraw` replaces them, which gives another eye with the same parameters:
what :mod:`invglare.fit.draw_scatter` simulates to measure the scatter between eyes, and
what a fit of statistics averages over (a view's ``model_draws``).
"""

from __future__ import annotations

from typing import Any

import jax
from jaxtyping import Array


def _is_key(leaf: Any) -> bool:
    return isinstance(leaf, jax.Array) and jax.dtypes.issubdtype(leaf.dtype, jax.dtypes.prng_key)


def random_keys(tree: Any) -> int:
    """How many random keys (typed `jax.random` keys) `tree` holds: its random draws."""
    return sum(_is_key(leaf) for leaf in jax.tree_util.tree_leaves(tree))


def redraw(tree: Any, key: Array) -> Any:
    """`tree` with its `j`-th random key replaced by ``fold_in(key, j)``: another draw.

    Every random component (a pool of lashes drawn from its key, particles, gratings,
    a camera's dust) draws anew; what has no key (a fitted lash layout, the pupil) stays.
    Works under `jit` and `vmap` over `key`.
    """
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    out, j = [], 0
    for leaf in leaves:
        if _is_key(leaf):
            leaf = jax.random.fold_in(key, j)
            j += 1
        out.append(leaf)
    return jax.tree_util.tree_unflatten(treedef, out)


#: Seed of the extra draws a prediction is averaged over (fixed: common random numbers).
MODEL_DRAW_SEED = 20261201


def mean_prediction(forward: Any, n: int) -> tuple[Array, Array]:
    """``(expected, predicted)`` of `forward` averaged over `n` eyes: its own draw and
    ``n - 1`` redrawn ones (fixed keys, so the same at every call).

    The expected photo of an eye drawn at random with these parameters, estimated from
    `n` draws: a statistic of it follows the parameters with ``sqrt(n)`` times less of one
    draw's jaggedness.
    """
    expected = forward.expected()
    if n > 1:
        keys = jax.random.split(jax.random.key(MODEL_DRAW_SEED), n - 1)
        others = jax.vmap(lambda k: redraw(forward, k).expected())(keys)
        expected = (expected + others.sum(axis=0)) / n
    return expected, forward.obs.clip(expected)
