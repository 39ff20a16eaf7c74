"""Posterior sampling of a fit with emcee: log-probability, walkers, checkpoints, convergence.

**Where the sampler walks.** emcee moves the walkers in the *latent* space of the
:class:`~invglare.fit.ParameterSpace` (logit / log / identity transforms, see
:mod:`invglare.fit.params`), where bounded parameters are unbounded and the
affine-invariant moves never propose an impossible value. The density it
samples is therefore the physical posterior times the Jacobian of the transform,

```
log p(z) = log L(data | x(z)) + log prior(x(z)) + sum_i log |dx_i / dz_i|
```

so that the *physical* values ``x(z)`` are distributed as the posterior
``L(data | x) prior(x)``, with the priors in physical units. The physical values
of every step are stored next to the latent chain (emcee "blobs"), and every
summary is of the physical values.

**Likelihood.** ``likelihood="pixels"`` (default) is the Poisson–Gaussian
likelihood of the observation model,
:meth:`invglare.fit.Observation.log_likelihood` (saturated pixels censored).
``likelihood="views"`` is the Gaussian pseudo-likelihood of the fit's weighted
residuals, ``-sum(r**2) / (2 s**2)`` with ``s**2`` the fit's
`covariance_scale`: use it when the fit compares statistics (radial profile,
angular energy) rather than pixels, e.g. for needles whose exact positions are
not modelled.

**Evaluation.** The log-probability is one `jax.jit`-ed, `jax.vmap`-ed program
over a batch of walkers, handed to ``emcee.EnsembleSampler(..., vectorize=True)``;
emcee asks for half the ensemble at a time (a quarter for the DE-snooker move),
which is cut into balanced batches of at most `batch_size` walkers. Larger
batches amortise the dispatch; beyond a few walkers on a CPU the cost per walker
is flat, and very large ones spill the caches, so ``batch_size="auto"`` times
the candidates on the starting walkers and keeps the fastest per walker. Measured
on a shared 2-core CPU (3 free parameters, ms per walker for batches of 1, 2, 4,
8, 16): a 64² disk photo 1.3, 0.72, 0.63, 0.96, 0.84; a 256² one 28, 29, 32, 26,
36 (there the model's FFTs dominate and batching gains little).

**Checkpoints.** The chain lives in an HDF5 file (:class:`emcee.backends.HDFBackend`);
every completed step is written before the next one starts. Ctrl-C and a plain
``kill`` (SIGTERM) are deferred while a step is being written, so an
interrupted run loses only the step in progress, and ``resume=True`` continues
from the last stored step with the stored random state (the resumed chain is
the one an uninterrupted run would have produced). A SIGKILL during the
sub-millisecond write itself can still damage the file.

**Convergence.** Every `check_every` steps the integrated autocorrelation time
τ of each parameter is estimated (emcee's estimator); the run stops once the
chain is longer than `tau_factor` (50) τ for every parameter and τ changed by less
than `tau_rtol` since the last check, or at `max_steps`. Warnings a user can act
on are collected in :attr:`SampleResult.warnings`.

**Example:**

```python
from invglare.fit import fit
from invglare.fit.sample import sample

res = fit(space, forward, photo)
post = sample(space, forward, photo, res, "chain.h5", n_walkers=32, max_steps=5000)
print(post.summary())
```
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import functools
import hashlib
import json
import math
import os
import signal
import threading
import time
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import emcee
import equinox as eqx
import h5py
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int
from scipy.special import ndtr

from invglare.errors import ConfigError, InputDataError, NumericalError
from invglare.fit.observation import CENSORING, Forward, check_target
from invglare.fit.params import ParameterSpace
from invglare.fit.result import FitResult
from invglare.fit.specialise import specialise_forward
from invglare.fit.views import ResidualFn, make_residual_fn

__all__ = [
    "MOVES",
    "BatchedLogProb",
    "LogPosterior",
    "SampleProgress",
    "SampleResult",
    "check_priors",
    "diagnose",
    "fingerprint",
    "initial_walkers",
    "load_chain",
    "make_log_posterior",
    "parse_moves",
    "sample",
    "tune_batch_size",
]

#: The space emcee walks in (see the module docstring).
SAMPLING_SPACE = "latent"

#: Moves selectable by name: emcee's move classes.
MOVES: dict[str, type] = {
    "stretch": emcee.moves.StretchMove,
    "de": emcee.moves.DEMove,
    "de_snooker": emcee.moves.DESnookerMove,
    "kde": emcee.moves.KDEMove,
    "walk": emcee.moves.WalkMove,
}

LIKELIHOODS = ("pixels", "views")

#: Name of the emcee group in the HDF5 file, and of the group holding our metadata.
CHAIN_GROUP = "mcmc"
META_GROUP = "invglare"
FORMAT = "invglare.chain"
VERSION = 1

#: A prior holding less than this fraction of its probability inside the bounds is refused.
MIN_PRIOR_MASS = 1e-12


# --------------------------------------------------------------------------------------
# priors


def prior_mass(space: ParameterSpace) -> dict[str, float]:
    """Fraction of each parameter's prior probability that lies inside its bounds.

    Uniform priors count as 1 (they are the bounds). ``normal``:
    ``Phi((upper - mean) / std) - Phi((lower - mean) / std)``; ``lognormal``: the
    same in ``log x`` with ``log(max(lower, 0))``.

    **Example:** a ``("normal", 10.0, 0.5)`` prior on a parameter bounded to
    ``[2, 5]`` has mass ``~1e-23`` inside: the prior and the bounds disagree.
    """
    out = {}
    for p in space.all:
        prior = p.prior
        if prior is None or prior.kind == "uniform":
            out[p.path] = 1.0
            continue
        lo, hi = p.lower, p.upper
        if prior.kind == "lognormal":
            if hi <= 0:
                out[p.path] = 0.0
                continue
            lo = math.log(lo) if lo > 0 else -math.inf
            hi = math.log(hi) if math.isfinite(hi) else math.inf
        a = (lo - prior.mean) / prior.std
        b = (hi - prior.mean) / prior.std
        # Subtract in the tail where the difference keeps its digits.
        mass = float(ndtr(b) - ndtr(a)) if a < 0 else float(ndtr(-a) - ndtr(-b))
        out[p.path] = max(mass, 0.0)
    return out


def check_priors(space: ParameterSpace) -> None:
    """Refuse priors that put (essentially) no probability inside their parameter's bounds.

    Raises :class:`~invglare.errors.ConfigError` naming the parameter, its prior,
    its bounds and the mass inside (below :data:`MIN_PRIOR_MASS`).
    """
    for p in space.all:
        mass = prior_mass(space)[p.path]
        if mass < MIN_PRIOR_MASS:
            pr = p.prior
            raise ConfigError(
                f"the {pr.kind}(mean={pr.mean:g}, std={pr.std:g}) prior of {p.path!r} puts "
                f"{mass:.1e} of its probability inside the bounds [{p.lower:g}, {p.upper:g}]: "
                "the prior and the bounds contradict each other (a lognormal's mean is of "
                "log x); fix the prior's mean / std or the bounds"
            )


# --------------------------------------------------------------------------------------
# the log-probability


class LogPosterior(eqx.Module):
    """The log posterior density of the latent vector of a fit, for one walker.

    ``lp(z) = log L(target | x(z)) + log prior(x(z)) + log |det dx/dz|``: its samples
    in `z` map to physical samples ``x(z)`` of the posterior (module docstring).
    Call it on one latent vector; `jax.vmap` it over walkers.

    Build it with :func:`make_log_posterior`.
    """

    space: ParameterSpace = eqx.field(static=True)
    forward: Forward
    target: Float[Array, "h w"]
    mask: Bool[Array, "h w"] | None
    residual_fn: ResidualFn | None
    #: Flat indices of the target's saturated pixels in use (see `Observation.log_likelihood`).
    censored: Int[Array, " k"] | None
    censoring: str = eqx.field(static=True, default="survival")
    likelihood: str = eqx.field(static=True, default="pixels")
    residual_scale: float = eqx.field(static=True, default=1.0)

    def log_likelihood(self, latent: Float[Array, " p"]) -> Float[Array, ""]:
        """The log-likelihood at latent `latent` (see the module docstring)."""
        if self.likelihood == "views":
            r = self.residual_fn(latent, None)
            return -0.5 * jnp.sum(r * r) / self.residual_scale
        fwd = self.space.apply(self.forward, self.space.from_latent(latent))
        expected = fwd.expected()
        return fwd.obs.log_likelihood(
            self.target, expected, censoring=self.censoring, mask=self.mask, censored=self.censored
        )

    def log_prior(self, latent: Float[Array, " p"]) -> Float[Array, ""]:
        """Log prior of the physical values plus the log-Jacobian of the latent transform."""
        x = self.space.from_latent(latent)
        return self.space.log_prior(x) + self.space.log_det_jacobian(latent)

    def __call__(self, latent: Float[Array, " p"]) -> Float[Array, ""]:
        prior = self.log_prior(latent)
        # Outside the prior's support the model may not even be defined (a negative
        # diameter): -inf, whatever the likelihood says there.
        ok = jnp.isfinite(prior)
        return jnp.where(ok, prior + self.log_likelihood(latent), -jnp.inf)


def make_log_posterior(
    space: ParameterSpace,
    forward_template: Forward,
    target: Float[ArrayLike, "h w"],
    *,
    likelihood: str = "pixels",
    censoring: str = "survival",
    mask: Bool[ArrayLike, "h w"] | None = None,
    views: Mapping[str, float] | None = None,
    view_options: Mapping[str, Mapping[str, Any]] | None = None,
    residual_scale: float = 1.0,
) -> LogPosterior:
    """Build the log posterior of a fit, validating the space, priors, target and options.

    **Arguments:**

    - `space`, `forward_template`, `target`: as for :func:`invglare.fit.fit`.
    - `likelihood`: ``"pixels"`` (Poisson–Gaussian, the default) or ``"views"``
      (Gaussian on the fit's residuals; needs `views`, optionally `view_options`,
      and `residual_scale`, the fit's `covariance_scale`).
    - `censoring`: how saturated pixels enter the pixel likelihood (``"survival"``
      or ``"exclude"``, see :meth:`~invglare.fit.Observation.log_likelihood`).
    - `mask`: pixels to use (True), e.g. to drop hot pixels.

    **Returns:** a :class:`LogPosterior`.

    **Example:**

    ```python
    lp = make_log_posterior(space, Forward(model, obs), photo)
    lp(space.initial_latent())            # one walker
    jax.vmap(lp)(walkers)                 # many
    ```
    """
    if likelihood not in LIKELIHOODS:
        raise ConfigError(f"likelihood {likelihood!r} is not one of {', '.join(LIKELIHOODS)}")
    if censoring not in CENSORING:
        raise ConfigError(f"censoring {censoring!r} is not one of {', '.join(CENSORING)}")
    if not isinstance(forward_template, Forward):
        raise ConfigError(
            f"forward_template must be a Forward(model, obs), got {type(forward_template).__name__}"
        )
    space.check(forward_template)
    forward_template = specialise_forward(space, forward_template)
    check_priors(space)
    if not (math.isfinite(residual_scale) and residual_scale > 0):
        raise ConfigError(f"residual_scale must be finite and > 0, got {residual_scale!r}")
    out_shape = eqx.filter_eval_shape(forward_template).shape
    tgt = check_target(target, shape=out_shape, saturation=forward_template.obs.saturation)
    residual_fn = None
    if likelihood == "views":
        if not views:
            raise ConfigError("likelihood='views' needs the fit's views, e.g. {'radial': 1.0}")
        residual_fn = make_residual_fn(
            space, forward_template, tgt, views, view_options=view_options
        )
    m = None
    if mask is not None:
        m = jnp.asarray(mask, bool)
        if m.shape != tuple(out_shape):
            raise ConfigError(f"mask has shape {m.shape}, expected the photo's {tuple(out_shape)}")
    return LogPosterior(
        space=space,
        forward=forward_template,
        target=_float64(tgt),
        mask=m,
        residual_fn=residual_fn,
        censored=jnp.asarray(forward_template.obs.censored_indices(tgt, m), jnp.int32),
        censoring=censoring,
        likelihood=likelihood,
        residual_scale=float(residual_scale),
    )


def _float64(a) -> Array:
    with jax.enable_x64(True):
        return jnp.asarray(a, dtype=jnp.float64)


def fingerprint(log_posterior: LogPosterior) -> str:
    """A short hash of the data and fixed values a log posterior is made of.

    Stored with a chain so that resuming it against another photo, another fixed
    value or another likelihood setting is refused: its steps would not be draws
    from the new posterior.
    """
    h = hashlib.sha256()
    h.update(f"{log_posterior.likelihood}|{log_posterior.censoring}|".encode())
    h.update("|".join(log_posterior.space.paths).encode())
    # The censored indices follow from the target, mask and clip level: not hashed, so
    # that chains stored before they existed keep their fingerprint.
    data = eqx.tree_at(lambda lp: lp.censored, log_posterior, None, is_leaf=lambda x: x is None)
    for leaf in jax.tree_util.tree_leaves(eqx.filter(data, eqx.is_array)):
        if jax.dtypes.issubdtype(leaf.dtype, jax.dtypes.prng_key):  # a model's random draw
            leaf = jax.random.key_data(leaf)
        a = np.ascontiguousarray(np.asarray(leaf))
        h.update(f"{a.dtype}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


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


# --------------------------------------------------------------------------------------
# moves


def parse_moves(moves: str | Mapping[str, float] | Sequence | None) -> list[tuple[str, float]]:
    """Normalise a move specification to ``[(name, weight), ...]`` with weights summing to 1.

    Accepts a name (``"stretch"``, ``"de"``, ``"de_snooker"``, ``"kde"``,
    ``"walk"``), a mapping ``{"de": 0.8, "de_snooker": 0.2}`` or a list of names
    or ``(name, weight)`` pairs. ``None`` is the stretch move.
    """
    if moves is None:
        moves = "stretch"
    if isinstance(moves, str):
        items = [(moves, 1.0)]
    elif isinstance(moves, Mapping):
        items = list(moves.items())
    elif isinstance(moves, Sequence):
        items = [(m, 1.0) if isinstance(m, str) else tuple(m) for m in moves]
    else:
        raise ConfigError(
            f"moves must be a name, a mapping name -> weight or a list, got {moves!r}"
        )
    out = []
    for item in items:
        if len(item) != 2:
            raise ConfigError(f"a move must be a name or (name, weight), got {item!r}")
        name, weight = item
        if name not in MOVES:
            raise ConfigError(f"unknown move {name!r}; valid moves: {', '.join(MOVES)}")
        try:
            w = float(weight)
        except (TypeError, ValueError):
            raise ConfigError(
                f"the weight of move {name!r} must be a number, got {weight!r}"
            ) from None
        if not (math.isfinite(w) and w > 0):
            raise ConfigError(f"the weight of move {name!r} must be finite and > 0, got {weight!r}")
        out.append((str(name), w))
    if not out:
        raise ConfigError("moves is empty; give at least one, e.g. 'stretch'")
    total = sum(w for _, w in out)
    return [(n, w / total) for n, w in out]


def _emcee_moves(spec: list[tuple[str, float]]) -> list:
    return [(MOVES[name](), w) for name, w in spec]


# --------------------------------------------------------------------------------------
# initialisation


def _check_fit_matches(space: ParameterSpace, fit_result: FitResult) -> None:
    if list(fit_result.paths) != list(space.paths):
        raise InputDataError(
            f"the fit result is for the parameters {list(fit_result.paths)} but this space "
            f"frees {list(space.paths)}: it comes from another model or config; run the fit "
            "of this config again"
        )


@functools.partial(jax.jit, static_argnums=0)
def _latent_and_slope(space: ParameterSpace, x: Array) -> tuple[Array, Array]:
    # One compiled program: run eagerly, each transform op would compile on its own.
    z = space.to_latent(x)
    return z, space.jacobian_diag(z)


@functools.partial(jax.jit, static_argnums=0)
def _physical(space: ParameterSpace, z: Array) -> Array:
    return space.from_latent(z)


def _latent_covariance(
    space: ParameterSpace, fit_result: FitResult, d: np.ndarray
) -> tuple[np.ndarray, list[str]]:
    """The fit covariance mapped to latent space (``D^-1 C D^-1``, NaN entries replaced)."""
    notes: list[str] = []
    cov = np.asarray(fit_result.covariance, dtype=float)
    cz = cov / np.outer(d, d)
    bad = ~np.isfinite(np.diag(cz)) | (np.diag(cz) <= 0)
    bad |= ~np.all(np.isfinite(cz), axis=1)
    if bad.any():
        # An unconstrained parameter has no variance: a 1 % spread in the latent (a 1 %
        # relative one for log / logit transforms) lets the ensemble find its own width.
        names = [space.paths[i] for i in np.flatnonzero(bad)]
        notes.append(
            f"the fit gives no finite variance for {', '.join(names)}: walkers start 0.01 "
            "(latent units) around the fit value there"
        )
        cz[bad, :] = 0.0
        cz[:, bad] = 0.0
        cz[bad, bad] = 1e-4
    cz = 0.5 * (cz + cz.T)
    # Keep it positive definite: a degenerate pair gets a small spread along its null
    # direction instead of none (emcee's ensemble must span every dimension).
    w, v = np.linalg.eigh(cz)
    floor = max(float(w.max()), 1e-12) * 1e-8
    w = np.maximum(w, floor)
    return (v * w) @ v.T, notes


def initial_walkers(
    space: ParameterSpace,
    fit_result: FitResult,
    n_walkers: int,
    *,
    scale: float = 0.1,
    seed: int = 0,
    force: bool = False,
    log_prob: BatchedLogProb | Callable[[np.ndarray], np.ndarray] | None = None,
) -> Float[np.ndarray, "n p"]:
    """Latent starting points: a small ball around the fit, shaped by its covariance.

    Walker ``k`` is ``z0 + scale * L e_k`` with ``z0`` the fit's optimum in latent
    space, ``L L^T`` the fit covariance mapped to latent space (``D^-1 C D^-1``,
    ``D = diag(dx/dz)``) and ``e_k`` standard normal, so `scale` is in units of the
    fit's standard errors. Walkers whose physical values leave the bounds or whose
    log-probability is not finite are redrawn with half the spread, up to 20 times.
    `log_prob` is a :class:`BatchedLogProb` or any ``(n, p) -> (n,)`` function;
    it is always called with `n_walkers` rows (one compiled batch shape).

    Raises :class:`~invglare.errors.NumericalError` if the fit did not converge
    (unless `force`), if the log-probability at the fit or next to it is NaN, at
    the fit ``-inf``, or if no valid ball can be drawn;
    :class:`~invglare.errors.InputDataError` if the fit is for other parameters
    or a fit value lies on its bound (with `force`, the start is moved 0.1 % of
    the range inside instead).

    **Example:** ``initial_walkers(space, fit_result, 32, log_prob=BatchedLogProb(lp))``.
    """
    _check_fit_matches(space, fit_result)
    if not fit_result.converged and not force:
        raise NumericalError(
            f"the fit did not converge ({fit_result.message}); walkers started around a "
            "point that is not the optimum spend the chain on burn-in and may miss the "
            "mode. Rerun the fit (more starts, larger max_steps) or pass force=True "
            "(invglare sample --force) to sample anyway"
        )
    if int(n_walkers) != n_walkers or n_walkers < 2 * space.size or n_walkers % 2:
        raise ConfigError(
            f"n_walkers must be an even integer >= 2 x {space.size} parameters = "
            f"{2 * space.size}, got {n_walkers!r}"
        )
    if not (math.isfinite(scale) and scale > 0):
        raise ConfigError(f"the initial ball scale must be finite and > 0, got {scale!r}")
    x0 = np.array([fit_result.values[p] for p in space.paths], dtype=float)
    for i, (p, v) in enumerate(zip(space.all, x0, strict=True)):
        on_bound = (v <= p.lower or v >= p.upper) if p.kind != "identity" else False
        if not (on_bound or not (p.lower <= v <= p.upper) or not math.isfinite(v)):
            continue
        if force and math.isfinite(v):
            # Forced: start just inside (a logit / log latent on its bound is infinite).
            width = p.upper - p.lower if math.isfinite(p.upper - p.lower) else abs(v) + 1.0
            x0[i] = min(max(v, p.lower + 1e-3 * width), p.upper - 1e-3 * width)
            continue
        raise InputDataError(
            f"the fit value {v:g} of {p.path!r} is on or outside its bounds "
            f"[{p.lower:g}, {p.upper:g}]: the posterior piles at the bound; widen the "
            "bounds (if physical) and refit, or pass force=True (--force) to start just "
            "inside"
        )
    with jax.enable_x64(True):
        z0, d = (np.asarray(a, dtype=float) for a in _latent_and_slope(space, jnp.asarray(x0)))
    if not (np.all(np.isfinite(z0)) and np.all(np.isfinite(d)) and np.all(d > 0)):
        raise InputDataError(
            f"the fit values {space.as_dict(x0)} are too close to their bounds to be "
            "represented in latent space; widen the bounds and refit"
        )
    cz, _ = _latent_covariance(space, fit_result, d)

    def evaluate(z: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        # Padded to n_walkers rows with copies of z0, so every call has the same shape.
        k = z.shape[0]
        full = np.concatenate([z, np.repeat(z0[None, :], n_walkers - k, axis=0)])
        if isinstance(log_prob, BatchedLogProb):
            lp, x = log_prob.evaluate(full)
            return lp[:k], x[:k]
        return np.asarray(log_prob(full), dtype=float).reshape(n_walkers)[:k], None

    if log_prob is not None:
        lp0 = float(evaluate(z0[None, :])[0][0])
        if not np.isfinite(lp0):
            what = "NaN" if math.isnan(lp0) else "-inf (zero probability)"
            raise NumericalError(
                f"the log-probability at the fit optimum {space.as_dict(x0)} is {what}: "
                "check the target for bad pixels, the priors (is the fit value inside "
                "each prior's support?) and that the model renders there"
            )
    rng = np.random.default_rng(seed)
    chol = np.linalg.cholesky(cz)
    walkers = np.empty((n_walkers, space.size))
    todo = np.arange(n_walkers)
    s = scale
    for _ in range(20):
        draw = z0 + s * rng.standard_normal((todo.size, space.size)) @ chol.T
        lp, x = evaluate(draw) if log_prob is not None else (np.zeros(todo.size), None)
        if x is None:
            with jax.enable_x64(True):
                padded = np.concatenate([draw, np.repeat(z0[None], n_walkers - todo.size, 0)])
                x = np.asarray(_physical(space, jnp.asarray(padded)), dtype=float)[: todo.size]
        if np.isnan(lp).any():
            xb = space.as_dict(x[np.flatnonzero(np.isnan(lp))[0]])
            raise NumericalError(
                f"the log-probability is NaN at a start {xb} next to the fit: the model "
                "or the likelihood breaks down there (check the target for bad pixels "
                "and the model for values it cannot render)"
            )
        ok = np.all(np.isfinite(x), axis=1) & np.isfinite(lp)
        for i, p in enumerate(space.all):
            if p.kind == "identity":
                ok &= (x[:, i] >= p.lower) & (x[:, i] <= p.upper)
            else:  # a logit / log value rounded onto its bound has an infinite latent
                ok &= (x[:, i] > p.lower) & (x[:, i] < p.upper)
        walkers[todo[ok]] = draw[ok]
        todo = todo[~ok]
        if todo.size == 0:
            return walkers
        s *= 0.5
    raise NumericalError(
        f"could not place {todo.size} of {n_walkers} walkers inside the bounds with a finite "
        "log-probability around the fit: the fit sits at a bound or the covariance is "
        "unreliable; check the fit, or pass a smaller init scale"
    )


def _spans_all_dimensions(walkers: np.ndarray) -> bool:
    centred = walkers - walkers.mean(axis=0)
    scale = centred.std(axis=0)
    if np.any(scale == 0):
        return False
    sv = np.linalg.svd(centred / scale, compute_uv=False)
    return bool(sv[-1] > 1e-8 * sv[0])


# --------------------------------------------------------------------------------------
# checkpointing


@contextlib.contextmanager
def _deferred_signals() -> Iterator[None]:
    """Hold Ctrl-C (and SIGTERM) while a step is written; deliver it afterwards."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []

    def hold(signum, frame):
        received.append(signum)

    old = {s: signal.signal(s, hold) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        if received:
            handler = old[received[0]]
            if callable(handler):  # the run's own handler (records the request) or Python's
                handler(received[0], None)
            # Both become KeyboardInterrupt: the caller's clean-up and messages are the same.
            raise KeyboardInterrupt


class _StopRequests:
    """Ctrl-C and a plain ``kill`` (SIGTERM) during a run, as KeyboardInterrupt.

    The handler raises KeyboardInterrupt at once (to stop a long evaluation), and
    also records the request: Python swallows an exception raised while a weakref
    callback or ``__del__`` runs, so the run loop re-raises after the step in
    progress if the first one got lost.
    """

    def __init__(self):
        self.received = False
        self._old: dict[int, Any] = {}

    def _stop(self, signum, frame):
        self.received = True
        raise KeyboardInterrupt

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            self._old = {s: signal.signal(s, self._stop) for s in (signal.SIGINT, signal.SIGTERM)}
        return self

    def __exit__(self, *exc):
        for s, h in self._old.items():
            signal.signal(s, h)
        return False

    def check(self) -> None:
        if self.received:
            raise KeyboardInterrupt


#: How long a writer waits for a file another process (a reader) holds locked.
LOCK_WAIT_S = 30.0


def _open_for_writing(path, mode: str = "a"):
    """``h5py.File(path, mode)``, waiting while another process holds the file's lock.

    HDF5 locks a file while it is open; a user peeking at the chain with h5py (or
    emcee's backend) while the sampler runs must not make the next step's write
    fail and end a long run.
    """
    deadline = time.monotonic() + LOCK_WAIT_S
    while True:
        try:
            return h5py.File(path, mode)
        except BlockingIOError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)


def _read_chain(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """``(latent, physical blobs, log_prob, accepted, iteration)`` of the stored steps.

    Read without taking the file lock, so that reading a running chain never
    blocks the sampler's next write; only the first ``iteration`` steps (the
    counter is written last) are read, which are complete.
    """
    try:
        with h5py.File(path, "r", locking=False) as f:
            g = f[CHAIN_GROUP]
            it = int(g.attrs["iteration"])
            latent = g["chain"][:it]
            blobs = g["blobs"][:it] if "blobs" in g else np.full_like(latent, np.nan)
            return latent, blobs, g["log_prob"][:it], g["accepted"][...], it
    except (OSError, KeyError) as err:
        raise InputDataError(
            f"cannot read the chain file {path}: {err}; it is damaged or not an emcee chain"
        ) from None


class _Backend(emcee.backends.HDFBackend):
    """emcee's HDF5 backend, writing a step in one file opening that Ctrl-C cannot tear.

    emcee's own `save_step` opens the file six times per step to validate shapes
    (``_check``); at ~2 ms per opening that cost more than the model on small
    photos. The shapes are fixed by the sampler that calls it, so this writes the
    same datasets and attributes, in the same order (the iteration counter last,
    so a step is only counted once all of it is there), with one opening.
    """

    def open(self, mode="r"):
        if mode == "r":
            return super().open(mode)
        f = _open_for_writing(self.filename, mode)
        if not self.dtype_set and self.name in f and "chain" in f[self.name]:
            self.dtype = f[self.name]["chain"].dtype
            self.dtype_set = True
        return f

    def save_step(self, state, accepted):
        with _deferred_signals(), self.open("a") as f:
            g = f[self.name]
            iteration = g.attrs["iteration"]
            g["chain"][iteration, :, :] = state.coords
            g["log_prob"][iteration, :] = state.log_prob
            if state.blobs is not None:
                g["blobs"][iteration, :] = state.blobs
            g["accepted"][:] += accepted
            for i, v in enumerate(state.random_state):
                g.attrs[f"random_state_{i}"] = v
            g.attrs["iteration"] = iteration + 1

    def grow(self, ngrow, blobs):
        with _deferred_signals():
            super().grow(ngrow, blobs)


def _read_meta(path: Path) -> dict[str, Any] | None:
    try:
        with h5py.File(path, "r", locking=False) as f:
            if META_GROUP not in f:
                return None
            return json.loads(f[META_GROUP].attrs["meta"])
    except (OSError, KeyError, ValueError) as err:
        raise InputDataError(
            f"cannot read the chain file {path}: {err}; it is damaged or not an invglare "
            "chain (move it away and sample again without resume)"
        ) from None


def _write_meta(path: Path, meta: dict[str, Any]) -> None:
    with _deferred_signals(), _open_for_writing(path) as f:
        g = f.require_group(META_GROUP)
        g.attrs["meta"] = json.dumps(meta)


def _stored_iteration(path: Path) -> int:
    try:
        with h5py.File(path, "r", locking=False) as f:
            if CHAIN_GROUP not in f:
                return 0
            return int(f[CHAIN_GROUP].attrs["iteration"])
    except (OSError, KeyError) as err:
        raise InputDataError(
            f"cannot read the chain file {path}: {err}; it is damaged or not an emcee chain"
        ) from None


# --------------------------------------------------------------------------------------
# results and diagnostics


class SampleProgress(NamedTuple):
    """One progress report, after each completed (and stored) step."""

    iteration: int
    max_steps: int
    acceptance: float
    tau_max: float


@dataclasses.dataclass
class SampleResult:
    """A chain with its diagnostics, in physical units.

    **Attributes:**

    - `paths`, `nuisance`: the parameters (order of the last axis) and which are nuisance.
    - `chain`: ``(steps, walkers, p)`` physical values; `latent`: the same in
      latent space (what emcee moved); `log_prob`: ``(steps, walkers)``.
    - `acceptance`: per-walker acceptance fraction.
    - `tau`: ``{path: integrated autocorrelation time}`` in steps (of the latent
      chain; NaN for a chain too short to estimate it at all).
    - `burn_in`, `thin`: steps discarded and kept-every used by :meth:`samples`
      (``2 max tau`` and ``min tau / 2``).
    - `converged`: longer than ``tau_factor`` τ for every parameter.
    - `warnings`: problems a user can act on, in words.
    - `moves`: ``[(name, weight)]`` of the last run; `runs`: every run (start
      step, moves, batch size, timing) recorded in the file.
    - `truth`, `fit_values`, `fit_stderr`: from the fit result, where known.
    - `timing`: seconds per step, per walker evaluation, compile time.
    - `path`: the HDF5 file.
    """

    paths: list[str]
    nuisance: list[str]
    chain: np.ndarray
    latent: np.ndarray
    log_prob: np.ndarray
    acceptance: np.ndarray
    tau: dict[str, float]
    burn_in: int
    thin: int
    converged: bool
    warnings: list[str]
    moves: list[tuple[str, float]]
    tau_factor: float = 50.0
    runs: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    truth: dict[str, float] | None = None
    fit_values: dict[str, float] = dataclasses.field(default_factory=dict)
    fit_stderr: dict[str, float] = dataclasses.field(default_factory=dict)
    timing: dict[str, float] = dataclasses.field(default_factory=dict)
    sampling_space: str = SAMPLING_SPACE
    likelihood: str = "pixels"
    path: Path | None = None

    @property
    def n_steps(self) -> int:
        return int(self.chain.shape[0])

    @property
    def n_walkers(self) -> int:
        return int(self.chain.shape[1])

    def samples(
        self, discard: int | None = None, thin: int | None = None, flat: bool = True
    ) -> np.ndarray:
        """Physical samples after burn-in: ``(n, p)`` if `flat`, else ``(steps, walkers, p)``."""
        d = self.burn_in if discard is None else int(discard)
        t = self.thin if thin is None else int(thin)
        out = self.chain[d::t]
        return out.reshape(-1, out.shape[-1]) if flat else out

    def effective_samples(self) -> dict[str, float]:
        """``walkers * (steps - burn_in) / tau`` per parameter."""
        n = self.n_walkers * max(self.n_steps - self.burn_in, 0)
        return {p: (n / t if t > 0 else math.nan) for p, t in self.tau.items()}

    def percentiles(self) -> dict[str, dict[str, float]]:
        """Per parameter: median, 16/84 and 2.5/97.5 percentiles, mean and std."""
        s = self.samples()
        out = {}
        for i, p in enumerate(self.paths):
            q = np.percentile(s[:, i], [2.5, 16, 50, 84, 97.5])
            out[p] = {
                "median": float(q[2]),
                "p16": float(q[1]),
                "p84": float(q[3]),
                "p2_5": float(q[0]),
                "p97_5": float(q[4]),
                "mean": float(s[:, i].mean()),
                "std": float(s[:, i].std(ddof=1)) if len(s) > 1 else math.nan,
            }
        return out

    def correlation(self) -> np.ndarray:
        """``(p, p)`` correlation matrix of the physical samples."""
        return np.corrcoef(self.samples(), rowvar=False).reshape(len(self.paths), -1)

    def summary(self) -> str:
        """A plain-text table: median with 16/84 percentiles, τ, truth where known."""
        pc = self.percentiles()
        head = (
            f"{self.n_steps} steps x {self.n_walkers} walkers, burn-in {self.burn_in}, "
            f"thin {self.thin}, acceptance {self.acceptance.mean():.3f}, "
            f"{'converged' if self.converged else 'NOT converged'}"
        )
        lines = [head]
        for p in self.paths:
            v = pc[p]
            line = (
                f"  {p}: {v['median']:.6g} +{v['p84'] - v['median']:.3g} "
                f"-{v['median'] - v['p16']:.3g}  (tau {self.tau[p]:.1f})"
            )
            if self.truth and p in self.truth:
                line += f"  truth {self.truth[p]:.6g}"
            lines.append(line)
        lines += [f"  warning: {w}" for w in self.warnings]
        return "\n".join(lines)


def _tau(latent: np.ndarray) -> np.ndarray:
    if latent.shape[0] < 2:
        return np.full(latent.shape[-1], np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        # tol=0: the estimate is returned whatever the chain length; the length check
        # against tau_factor is ours (so a short chain warns instead of raising).
        return np.asarray(emcee.autocorr.integrated_time(latent, c=5, tol=0, quiet=True))


def diagnose(
    chain: np.ndarray,
    latent: np.ndarray,
    log_prob: np.ndarray,
    acceptance: np.ndarray,
    space: ParameterSpace,
    *,
    tau_factor: float = 50.0,
    n_nan: int = 0,
) -> tuple[np.ndarray, int, int, bool, list[str]]:
    """τ, burn-in, thinning, convergence and warnings of a chain.

    Warnings (each says what to do): the chain is shorter than ``tau_factor`` τ;
    acceptance outside 0.15–0.85 (the stretch move accepts
    ~0.7 in one or two dimensions); stuck walkers (acceptance below a fifth of the
    median, or log-probability far below the rest); a parameter piling at a bound
    (more than 5 % of the samples within 2 % of the range from it); NaN
    log-probabilities. **Returns:** ``(tau, burn_in, thin, converged, warnings)``.
    """
    n_steps = chain.shape[0]
    tau = _tau(latent)
    notes: list[str] = []
    finite = np.isfinite(tau) & (tau > 0)
    tau_max = float(np.max(tau[finite])) if finite.any() else math.nan
    converged = bool(finite.all() and n_steps > tau_factor * tau_max)
    if finite.all():
        burn = min(math.ceil(2 * tau_max), n_steps // 2)
        thin = max(1, int(np.min(tau) / 2))
    else:
        burn, thin = n_steps // 3, 1
    if not converged:
        need = math.ceil(tau_factor * tau_max * 1.2) if math.isfinite(tau_max) else None
        worst = space.paths[int(np.nanargmax(np.where(finite, tau, -1.0)))] if finite.any() else ""
        notes.append(
            f"the chain ({n_steps} steps) is shorter than {tau_factor:g} autocorrelation times"
            + (
                f" (tau = {tau_max:.1f} steps for {worst!r} so far; a short chain "
                "underestimates it)"
                if worst
                else ""
            )
            + "; the estimates are unreliable: continue with resume=True (invglare sample "
            + "--resume)"
            + (f" and at least --steps {need}" if need else "")
        )
    acc = float(np.mean(acceptance)) if acceptance.size else math.nan
    if acc < 0.15:
        notes.append(
            f"the mean acceptance fraction is {acc:.3f} (0.2-0.5 is healthy): the walkers "
            "rarely move; try moves = 'de' (or {de = 0.8, de_snooker = 0.2}), or check "
            "for a multimodal or very narrow posterior"
        )
    elif acc > 0.85:
        notes.append(
            f"the mean acceptance fraction is {acc:.3f} (0.2-0.5 is healthy): the posterior "
            "may be nearly flat in some parameter (improper prior, unconstrained parameter); "
            "check the bounds and priors"
        )
    if n_steps >= 10:
        med = float(np.median(acceptance))
        stuck = set(np.flatnonzero(acceptance < 0.2 * med).tolist()) if med > 0 else set()
        tail = log_prob[n_steps // 2 :]
        mean_lp = np.mean(np.where(np.isfinite(tail), tail, -1e300), axis=0)
        lp_med = float(np.median(mean_lp))
        lp_spread = float(np.median(np.abs(mean_lp - lp_med))) + space.size
        stuck |= set(np.flatnonzero(mean_lp < lp_med - 10 * lp_spread).tolist())
        if stuck:
            ids = sorted(stuck)
            notes.append(
                f"{len(ids)} walker(s) look stuck ({', '.join(map(str, ids[:10]))}"
                f"{', ...' if len(ids) > 10 else ''}: low acceptance or log-probability far "
                "below the ensemble); they bias the summaries: restart from the fit with "
                "more walkers or moves = 'de', or check for a second mode"
            )
    post = chain[burn:].reshape(-1, chain.shape[-1])
    if post.shape[0] > 0:
        for i, p in enumerate(space.all):
            for b, side in ((p.lower, "lower"), (p.upper, "upper")):
                if not math.isfinite(b):
                    continue
                med = float(np.median(post[:, i]))
                if math.isfinite(p.lower) and math.isfinite(p.upper):
                    margin = 0.02 * (p.upper - p.lower)
                else:
                    margin = 0.05 * abs(med - b)
                frac = float(np.mean(np.abs(post[:, i] - b) <= margin))
                if frac > 0.05:
                    notes.append(
                        f"{p.path!r} piles at its {side} bound {b:g} ({100 * frac:.0f}% of "
                        "the samples within 2% of the range of it): the bound, not the "
                        "data, limits it; widen the bound if that is physical, or report "
                        "a one-sided limit"
                    )
    if n_nan:
        notes.append(
            f"{n_nan} proposal(s) gave a NaN log-probability and were rejected: the model "
            "breaks down somewhere inside the bounds; narrow the bounds to where it renders"
        )
    return tau, burn, thin, converged, notes


def load_chain(
    path: str | os.PathLike[str], space: ParameterSpace | None = None, *, tau_factor: float = 50.0
) -> SampleResult:
    """Read a chain written by :func:`sample` and diagnose it.

    `space` (the fit's parameter space) is checked against the stored paths and
    used for the bound checks; without it the bounds stored in the file are used.
    Raises :class:`~invglare.errors.InputDataError` if the file is missing,
    damaged, empty, or for other parameters.
    """
    p = Path(path)
    if not p.is_file():
        raise InputDataError(f"chain file {p} does not exist; run invglare sample first")
    meta = _read_meta(p)
    if meta is None or meta.get("format") != FORMAT:
        raise InputDataError(f"{p} is not an invglare chain (no {META_GROUP!r} metadata)")
    if space is not None and list(meta["paths"]) != list(space.paths):
        raise InputDataError(
            f"the chain {p} is for the parameters {meta['paths']} but the config frees "
            f"{list(space.paths)}: it is from another model or config"
        )
    if space is None:
        space = _space_from_meta(meta)
    if _stored_iteration(p) == 0:
        raise InputDataError(f"the chain file {p} holds no completed step yet")
    latent, blobs, log_prob, accepted, iteration = _read_chain(p)
    acceptance = accepted / iteration
    chain = np.asarray(blobs, dtype=float).reshape(latent.shape)
    tau, burn, thin, conv, notes = diagnose(
        chain, latent, log_prob, acceptance, space, tau_factor=tau_factor,
        n_nan=int(sum(r.get("n_nan", 0) for r in meta.get("runs", []))),
    )  # fmt: skip
    runs = meta.get("runs", [])
    last = runs[-1] if runs else {}
    return SampleResult(
        paths=list(meta["paths"]),
        nuisance=list(meta.get("nuisance", [])),
        chain=chain,
        latent=latent,
        log_prob=log_prob,
        acceptance=acceptance,
        tau={q: float(t) for q, t in zip(meta["paths"], tau, strict=True)},
        burn_in=burn,
        thin=thin,
        converged=conv,
        warnings=notes,
        moves=[tuple(m) for m in last.get("moves", [("stretch", 1.0)])],
        tau_factor=tau_factor,
        runs=runs,
        truth=meta.get("truth"),
        fit_values=meta.get("fit_values", {}),
        fit_stderr=meta.get("fit_stderr", {}),
        timing=dict(last.get("timing", {})),
        sampling_space=meta.get("sampling_space", SAMPLING_SPACE),
        likelihood=meta.get("likelihood", "pixels"),
        path=p,
    )


def _space_from_meta(meta: dict[str, Any]) -> ParameterSpace:
    from invglare.fit.params import Parameter

    params, nuis = [], []
    for b in meta["bounds"]:
        lo, hi = float(b["lower"]), float(b["upper"])
        init = b.get("fit_value")
        if init is None or not (lo < init < hi):
            init = (
                0.5 * (lo + hi) if math.isfinite(lo + hi) else (lo + 1 if math.isfinite(lo) else 0)
            )
        par = Parameter(b["path"], lo, hi, init=init, transform=b["transform"])
        (nuis if b["path"] in meta.get("nuisance", []) else params).append(par)
    return ParameterSpace(params, nuis)


# --------------------------------------------------------------------------------------
# the run


def _meta(space, fit_result, n_walkers, likelihood, fp) -> dict[str, Any]:
    return {
        "format": FORMAT,
        "version": VERSION,
        "fingerprint": fp,
        "paths": list(space.paths),
        "nuisance": [p.path for p in space.nuisance],
        "sampling_space": SAMPLING_SPACE,
        "likelihood": likelihood,
        "n_walkers": int(n_walkers),
        "bounds": [
            {
                "path": p.path,
                "lower": p.lower,
                "upper": p.upper,
                "transform": p.kind,
                "prior": None if p.prior is None else dataclasses.asdict(p.prior),
                "fit_value": fit_result.values.get(p.path),
            }
            for p in space.all
        ],
        "truth": fit_result.truth,
        "fit_values": dict(fit_result.values),
        "fit_stderr": {k: (v if math.isfinite(v) else None) for k, v in fit_result.stderr.items()},
        "fit_converged": bool(fit_result.converged),
        "runs": [],
    }


def sample(
    space: ParameterSpace,
    forward_template: Forward,
    target: Float[ArrayLike, "h w"],
    fit_result: FitResult,
    path: str | os.PathLike[str],
    *,
    n_walkers: int | None = None,
    max_steps: int = 5000,
    moves: str | Mapping[str, float] | Sequence | None = "stretch",
    resume: bool = False,
    restart: bool = False,
    force: bool = False,
    until_converged: bool = True,
    tau_factor: float = 50.0,
    tau_rtol: float = 0.05,
    check_every: int = 100,
    batch_size: int | str = "auto",
    init_scale: float = 0.1,
    seed: int = 0,
    likelihood: str = "pixels",
    censoring: str = "survival",
    mask: Bool[ArrayLike, "h w"] | None = None,
    views: Mapping[str, float] | None = None,
    view_options: Mapping[str, Mapping[str, Any]] | None = None,
    progress: bool | Callable[[SampleProgress], None] = True,
) -> SampleResult:
    """Sample the posterior of a fit with emcee, checkpointing every step to `path` (HDF5).

    **Arguments:**

    - `space`, `forward_template`, `target`: the fit's parameter space, forward
      model and photo (as for :func:`invglare.fit.fit`).
    - `fit_result`: the fit to start from (its optimum and covariance); refused
      if it did not converge, unless `force`.
    - `path`: the chain file. An existing chain is continued with `resume`,
      replaced with `restart`, and otherwise refused (nothing is overwritten).
    - `n_walkers`: even, at least twice the number of parameters (default
      ``max(32, 4 p)``); fixed by the stored chain when resuming.
    - `max_steps`: total steps, stored ones included (the step limit).
    - `moves`: see :func:`parse_moves`; recorded in the file for each run.
    - `until_converged`: stop early once the chain is longer than `tau_factor` τ
      for every parameter and τ moved by less than `tau_rtol` (relative) since the
      previous check, checked every `check_every` steps.
    - `batch_size`: walkers per compiled evaluation, or ``"auto"`` (timed, see
      :func:`tune_batch_size`).
    - `init_scale`: radius of the starting ball in units of the fit's standard errors.
    - `seed`: seeds the starting ball and emcee's random state (a resumed run
      continues the stored random state instead).
    - `likelihood`, `censoring`, `mask`, `views`, `view_options`: see
      :func:`make_log_posterior` (the views' residual scale is the fit's
      `covariance_scale`).
    - `progress`: a tqdm bar (True), none (False), or a callable receiving a
      :class:`SampleProgress` after every stored step (raising there stops the
      run; the steps so far are kept).

    **Returns:** a :class:`SampleResult` (also readable later with :func:`load_chain`).

    **Example:**

    ```python
    post = sample(space, forward, photo, fit_result, "reports/eye/posterior/chain.h5")
    post = sample(space, forward, photo, fit_result, "reports/eye/posterior/chain.h5",
                  resume=True, max_steps=20000)      # continue a run
    ```
    """
    t_setup = time.perf_counter()
    path = Path(path)
    _check_fit_matches(space, fit_result)
    spec = parse_moves(moves)
    if int(max_steps) != max_steps or max_steps < 1:
        raise ConfigError(f"max_steps must be an integer >= 1, got {max_steps!r}")
    if int(check_every) != check_every or check_every < 1:
        raise ConfigError(f"check_every must be an integer >= 1, got {check_every!r}")
    if not (tau_factor > 0 and tau_rtol > 0):
        raise ConfigError(f"tau_factor and tau_rtol must be > 0, got {tau_factor!r}, {tau_rtol!r}")
    if resume and restart:
        raise ConfigError("resume and restart exclude each other: continue the chain or replace it")
    lp = make_log_posterior(
        space, forward_template, target, likelihood=likelihood, censoring=censoring,
        mask=mask, views=views, view_options=view_options,
        residual_scale=fit_result.covariance_scale if likelihood == "views" else 1.0,
    )  # fmt: skip

    stored = _stored_iteration(path) if path.is_file() else 0
    if resume:
        if stored == 0:
            raise InputDataError(
                f"there is no chain to resume at {path}"
                + (" (it holds no step)" if path.is_file() else "")
                + "; run without --resume to start one"
            )
        meta = _read_meta(path)
        if meta is None or meta.get("format") != FORMAT:
            raise InputDataError(f"{path} is not an invglare chain; it cannot be resumed")
        if list(meta["paths"]) != list(space.paths):
            raise InputDataError(
                f"the chain {path} is for the parameters {meta['paths']} but the config frees "
                f"{list(space.paths)}: it is from another model or config; use restart"
            )
        if meta.get("fingerprint") != fingerprint(lp):
            raise InputDataError(
                f"the chain {path} was sampled for another photo, fixed value or likelihood "
                "setting than this one: its steps are not draws from this posterior; start "
                "a new chain with restart=True (--restart)"
            )
        stored_walkers = int(meta["n_walkers"])
        if n_walkers is not None and int(n_walkers) != stored_walkers:
            raise ConfigError(
                f"the stored chain has {stored_walkers} walkers, not {n_walkers}: a resumed "
                "run keeps its walkers (omit --walkers, or restart)"
            )
        n_walkers = stored_walkers
    else:
        if stored > 0 and not restart:
            raise ConfigError(
                f"{path} already holds a chain of {stored} steps; continue it with "
                "resume=True (--resume) or replace it with restart=True (--restart)"
            )
        if n_walkers is None:
            n_walkers = max(32, 4 * space.size)
            n_walkers += n_walkers % 2
        meta = _meta(space, fit_result, n_walkers, likelihood, fingerprint(lp))

    if batch_size != "auto" and (int(batch_size) != batch_size or batch_size < 1):
        raise ConfigError(f"batch_size must be an integer >= 1 or 'auto', got {batch_size!r}")
    # Until the batch size is tuned, a provisional one (its program is reused if it wins).
    probe = BatchedLogProb(lp, min(8, n_walkers // 2) if batch_size == "auto" else batch_size)

    if resume:
        # The last stored state, with its log-probabilities and random state: the run
        # continues exactly where it stopped.
        initial = emcee.backends.HDFBackend(
            str(path), CHAIN_GROUP, read_only=True
        ).get_last_sample()
        tune_walkers = initial.coords
    else:
        initial = initial_walkers(
            space, fit_result, n_walkers, scale=init_scale, seed=seed, force=force,
            log_prob=probe,
        )  # fmt: skip
        if not _spans_all_dimensions(initial):
            raise NumericalError(
                "the starting walkers do not span every parameter direction (the fit "
                "covariance is degenerate); raise init_scale or check the fit"
            )
        tune_walkers = initial
    if batch_size == "auto":
        half = tune_walkers[: max(1, n_walkers // 2)]
        batch_size, table = tune_batch_size(lp, half, repeats=2)
    else:
        table = {}
    f = BatchedLogProb(lp, int(batch_size))

    if restart and path.is_file():
        # Only now: a restart that fails to start must not have destroyed the old chain.
        path.unlink()
    path.parent.mkdir(parents=True, exist_ok=True)
    backend = _Backend(str(path), name=CHAIN_GROUP)
    if not resume:
        with _deferred_signals():
            backend.reset(n_walkers, space.size)
        _write_meta(path, meta)
    sampler = emcee.EnsembleSampler(
        n_walkers, space.size, f, moves=_emcee_moves(spec), backend=backend, vectorize=True
    )
    if not resume:
        sampler.random_state = np.random.RandomState(seed).get_state()

    run_info: dict[str, Any] = {
        "start_step": int(stored if resume else 0),
        "moves": [list(m) for m in spec],
        "batch_size": int(batch_size),
        "batch_timing_s_per_walker": {str(k): v for k, v in table.items()},
        "seed": int(seed),
        "started": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    bar = None
    if progress is True:
        from tqdm.auto import tqdm

        bar = tqdm(total=int(max_steps), initial=int(stored), unit="step", desc="sampling")
    callback = progress if callable(progress) else None
    t_start = time.perf_counter()
    # Compilation, batch-size tuning and the starting ball: everything before step 1.
    setup_s = t_start - t_setup
    done_steps = 0
    last_tau: np.ndarray | None = None
    tau_max = math.nan
    reason = "interrupted"
    try:
        with _StopRequests() as stop:
            state = initial
            while backend.iteration < max_steps:
                n = min(int(check_every), int(max_steps) - backend.iteration)
                steps = sampler.sample(
                    state, iterations=n, store=True, skip_initial_state_check=True
                )
                for new_state in steps:
                    stop.check()
                    state = new_state  # the next chunk continues from here
                    done_steps += 1
                    it = backend.iteration
                    if bar is not None:
                        bar.update(1)
                    if callback is not None:
                        acc = float(np.mean(sampler.acceptance_fraction))
                        callback(SampleProgress(it, int(max_steps), acc, tau_max))
                tau = _tau(backend.get_chain())
                tau_max = float(np.nanmax(tau)) if np.isfinite(tau).any() else math.nan
                if bar is not None:
                    bar.set_postfix(
                        tau=f"{tau_max:.1f}", acc=f"{np.mean(sampler.acceptance_fraction):.2f}"
                    )
                stable = last_tau is not None and np.all(np.abs(last_tau - tau) < tau_rtol * tau)
                long_enough = np.all(np.isfinite(tau)) and backend.iteration > tau_factor * tau_max
                last_tau = tau
                if until_converged and long_enough and stable:
                    reason = "converged"
                    break
            else:
                reason = "step limit"
    finally:
        if bar is not None:
            bar.close()
        elapsed = time.perf_counter() - t_start
        run_info["n_steps"] = int(done_steps)
        run_info["stopped"] = reason
        run_info["n_nan"] = int(f.n_nan)
        run_info["timing"] = {
            "total_s": elapsed,
            "s_per_step": elapsed / done_steps if done_steps else math.nan,
            "s_per_walker_eval": f.seconds_per_walker,
            "setup_s": setup_s,
            "batch_size": int(batch_size),
        }
        # The run record is written even on an interrupt, so the file says what happened.
        meta = _read_meta(path) or meta
        meta.setdefault("runs", []).append(run_info)
        _write_meta(path, meta)
    result = load_chain(path, space, tau_factor=tau_factor)
    result.timing = dict(run_info["timing"])
    return result
