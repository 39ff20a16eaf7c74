"""Starting walkers: a small ball around the fit, shaped by its covariance in latent space."""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from invglare.errors import ConfigError, InputDataError, NumericalError
from invglare.fit.params import ParameterSpace
from invglare.fit.result import FitResult
from invglare.fit.sample.batching import BatchedLogProb


def check_fit_matches(space: ParameterSpace, fit_result: FitResult) -> None:
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
    check_fit_matches(space, fit_result)
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


def spans_all_dimensions(walkers: np.ndarray) -> bool:
    centred = walkers - walkers.mean(axis=0)
    scale = centred.std(axis=0)
    if np.any(scale == 0):
        return False
    sv = np.linalg.svd(centred / scale, compute_uv=False)
    return bool(sv[-1] > 1e-8 * sv[0])
