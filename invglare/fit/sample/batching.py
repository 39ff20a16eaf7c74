"""Walkers evaluated in balanced batches by compiled, vmapped programs (emcee's ``vectorize``).

emcee asks for half the ensemble at a time (a quarter for the DE-snooker move); each
request is cut into batches of at most `batch_size` walkers, one compiled program per
batch shape, shared between log posteriors of the same structure.
"""

from __future__ import annotations

import collections
import math
import time
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from invglare.errors import ConfigError
from invglare.fit.sample.posterior import LogPosterior


def _batch_eval(dynamic, static, z):
    lp = eqx.combine(dynamic, static)
    return jax.vmap(lp)(z), lp.space.from_latent(z)


#: Compiled batch programs, shared by every BatchedLogProb of the same model structure,
#: data shapes and batch size (the arrays are inputs, so another photo reuses them).
_COMPILED: collections.OrderedDict = collections.OrderedDict()
_COMPILED_MAX = 16


class BatchedLogProb:
    """The numpy-in, numpy-out log-probability emcee calls with ``vectorize=True``.

    ``f(coords)`` with latent `coords` of shape ``(n, p)`` returns an ``(n, 1 + p)``
    array: the log-probability, then the physical values (emcee stores columns
    after the first as "blobs"). The walkers are cut into balanced batches of at
    most `batch_size`, each evaluated by one compiled, vmapped program (compiled
    once per batch shape). NaN log-probabilities are returned as ``-inf`` (the
    proposal is rejected) and counted in :attr:`n_nan`.

    Evaluation runs in float64: the log-likelihood is a sum over ~10⁵ pixels, and
    its float32 rounding (~0.01–0.1) is as large as the differences the
    acceptance test weighs.

    **Example:** ``BatchedLogProb(lp, 8)(np.zeros((16, lp.space.size)))``.
    """

    def __init__(self, log_posterior: LogPosterior, batch_size: int = 8):
        if int(batch_size) != batch_size or batch_size < 1:
            raise ConfigError(f"batch_size must be an integer >= 1, got {batch_size!r}")
        self.log_posterior = log_posterior
        self.batch_size = int(batch_size)
        self.n_nan = 0
        self.n_calls = 0
        self.n_evals = 0
        self.eval_s = 0.0
        self.compile_s = 0.0
        self._dynamic, self._static = eqx.partition(log_posterior, eqx.is_array)
        leaves, treedef = jax.tree_util.tree_flatten(self._dynamic)
        self._signature = (treedef, tuple((x.shape, x.dtype) for x in leaves), self._static)
        self._programs: dict[int, Any] = {}  # hashing the signature per call is not free

    @property
    def size(self) -> int:
        return self.log_posterior.space.size

    def _program(self, b: int):
        prog = self._programs.get(b)
        if prog is None:
            prog = self._programs[b] = self._shared_program(b)
        return prog

    def _shared_program(self, b: int):
        key = (*self._signature, b)
        try:
            prog = _COMPILED.get(key)
        except TypeError:  # something unhashable in the model's static part: no sharing
            key, prog = None, None
        if prog is None:
            t0 = time.perf_counter()
            z = jax.ShapeDtypeStruct((b, self.size), jnp.float64)
            prog = (
                jax.jit(_batch_eval, static_argnums=1).lower(self._dynamic, self._static, z)
            ).compile()
            self.compile_s += time.perf_counter() - t0
            if key is not None:
                _COMPILED[key] = prog
                while len(_COMPILED) > _COMPILED_MAX:
                    _COMPILED.popitem(last=False)
        elif key is not None:
            _COMPILED.move_to_end(key)
        return prog

    def evaluate(self, coords: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(log_prob (n,), physical (n, p))`` at latent `coords`, NaN kept as NaN."""
        z = np.asarray(coords, dtype=np.float64)
        if z.ndim != 2 or z.shape[1] != self.size:
            raise ConfigError(f"expected walkers of shape (n, {self.size}), got {z.shape}")
        n = z.shape[0]
        n_chunks = -(-n // self.batch_size)
        b = -(-n // n_chunks)  # balanced: ceil(n / n_chunks) <= batch_size
        with jax.enable_x64(True):
            prog = self._program(b)
            t0 = time.perf_counter()
            outs = []
            for k in range(n_chunks):
                chunk = z[k * b : (k + 1) * b]
                if chunk.shape[0] < b:  # pad with a valid walker; its result is dropped
                    pad = np.repeat(chunk[-1:], b - chunk.shape[0], axis=0)
                    chunk = np.concatenate([chunk, pad])
                # Dispatched asynchronously: the batches queue up while Python loops.
                outs.append(prog(self._dynamic, jnp.asarray(chunk)))
            lp = np.concatenate([np.asarray(o[0]) for o in outs])[:n]
            x = np.concatenate([np.asarray(o[1]) for o in outs])[:n]
            self.eval_s += time.perf_counter() - t0
        self.n_calls += 1
        self.n_evals += n
        return lp.astype(np.float64), x.astype(np.float64)

    def __call__(self, coords: np.ndarray) -> np.ndarray:
        lp, x = self.evaluate(coords)
        nan = np.isnan(lp)
        if nan.any():
            self.n_nan += int(nan.sum())
            lp = np.where(nan, -np.inf, lp)
        return np.column_stack([lp, x])

    @property
    def seconds_per_walker(self) -> float:
        return self.eval_s / self.n_evals if self.n_evals else math.nan


def tune_batch_size(
    log_posterior: LogPosterior,
    walkers: Float[ArrayLike, "n p"],
    candidates: Sequence[int] | None = None,
    *,
    repeats: int = 3,
) -> tuple[int, dict[int, float]]:
    """Time the candidate batch sizes on `walkers`; return the fastest and the table.

    Each candidate evaluates all rows of `walkers` (in batches of that size)
    `repeats` times after one warm-up (compilation excluded); the time is per
    walker. Candidates default to the powers of two up to ``len(walkers)``.

    **Returns:** ``(best batch size, {batch size: seconds per walker})``.
    """
    z = np.asarray(walkers, dtype=np.float64)
    n = z.shape[0]
    if candidates is None:
        candidates = [b for b in (1, 2, 4, 8, 16, 32, 64) if b <= n] or [n]
    table: dict[int, float] = {}
    for b in candidates:
        f = BatchedLogProb(log_posterior, int(b))
        f.evaluate(z)  # compile and warm up
        t0 = time.perf_counter()
        for _ in range(repeats):
            f.evaluate(z)
        table[int(b)] = (time.perf_counter() - t0) / (repeats * n)
    best = min(table, key=lambda k: table[k])
    return best, table
