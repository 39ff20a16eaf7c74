"""Draw-to-draw scatter of image statistics: what two eyes with the same parameters differ by.

A model with random structure (lashes drawn from a key, cornea cells, lens-nucleus and
vitreous particles, fibre gratings) predicts one eye of a population. A photo is of
another eye of that population: even at the true parameters its statistics (radial
profile, angular energy, halo radius) differ from the model's by the scatter between
draws, on top of the photon and read noise. A fit of those statistics that weighs its
residuals by the noise alone (or by their own sum of squares) mistakes that scatter for
information: its errors are too small and its estimates pulled by one draw.

This module measures the scatter at a point of the parameter space, by simulation: the
model with its random keys redrawn (:func:`~invglare.fit.redraw.redraw`) gives `draws`
other eyes, each observed with noise. For each statistics view (its residual
``r(t) = S(t) - S(model)``):

- ``offset`` = the mean over draws of ``r(noiseless photo of eye k)``: how far the
  model's prediction (its own draw, or the mean of `model_draws` eyes) sits from the
  population's mean statistic. Subtracted from the residual (a control variate): the
  level of the statistic then comes from many eyes, its change with the parameters from
  the model's own; measured at one point, it is right there and drifts away from it, so
  a stage with draws is repeated from its result with the scatter measured anew
  (:data:`invglare.fit.stages.DRAW_ROUNDS` rounds: a Gauss-Newton iteration on the
  population's mean statistic);
- ``C`` = ``Cov_k[r(noisy photo of eye k)] + Cov_k[r(noiseless photo of eye k)] / draws``:
  the scatter of a photo's statistic (another eye, and the noise) plus that of the
  offset's estimate, shrunk towards its diagonal (Schäfer & Strimmer 2005, target "D")
  so that it can be inverted with fewer draws than bins; ``whiten = L^{-1}`` with
  ``C = L L^T``.

The view returns ``whiten @ (r - offset)``: about N(0, I) at the true parameters,
correlations between bins included. :func:`scatter_covariance` then gives the standard
errors the scatter causes (a linearised bootstrap), correlations between views
included, whatever the whitening left out. Pixel views are left as they are (a pixel
residual of an unresolved draw has no such correction: fit those eyes through
statistics).

**Example:**

```python
fn = make_residual_fn(space, forward, photo, {"radial": 1.0, "angular": 1.0},
                      view_options={"radial": {"draws": 64}, "angular": {"draws": 64}})
options = scatter_options(fn, latent, {"radial": {"draws": 64}, "angular": {"draws": 64}})
result = fit(space, forward, photo, {"radial": 1.0, "angular": 1.0}, view_options=options)
```
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import equinox as eqx
import jax
import numpy as np
from jaxtyping import Array, Float

from invglare.fit.redraw import random_keys, redraw
from invglare.fit.views import ResidualFn, whitened

#: Draws evaluated per compiled call (a vmap): bounds the memory of a batch of models.
BATCH = 8


def _shrunk_covariance(x: np.ndarray) -> np.ndarray:
    """Covariance of the rows of `x` (draws x bins), shrunk towards its diagonal.

    Schäfer & Strimmer (2005), target D: the correlations are shrunk to 0 by the
    estimated ``lambda = sum Var(r_ij) / sum r_ij**2`` (off-diagonal), the variances
    kept. Bins without scatter get a tiny variance so that the result stays invertible.
    """
    k, n = x.shape
    xc = x - x.mean(axis=0)
    var = np.sum(xc * xc, axis=0) / (k - 1)
    sd = np.sqrt(np.maximum(var, 1e-300))
    z = xc / sd
    w = z[:, :, None] * z[:, None, :]  # (k, n, n)
    r = w.mean(axis=0) * k / (k - 1)
    var_r = k / (k - 1) ** 3 * np.sum((w - w.mean(axis=0)) ** 2, axis=0)
    off = ~np.eye(n, dtype=bool)
    denom = np.sum(r[off] ** 2)
    lam = 1.0 if denom <= 0 else float(np.clip(np.sum(var_r[off]) / denom, 0.0, 1.0))
    corr = (1.0 - lam) * r
    np.fill_diagonal(corr, 1.0)
    floor = 1e-12 * max(float(np.max(var)), 1e-300)
    sd = np.sqrt(np.maximum(var, floor))
    return corr * sd[:, None] * sd[None, :]


@eqx.filter_jit
def _draw_batch(fn: ResidualFn, latent: Array, keys: Array) -> tuple[list, list]:
    """Residuals of every view against `len(keys)` other eyes: noisy and noiseless photos."""
    fwd = fn.forward_at(latent)
    base = fn.context(latent)

    def one(key):
        k_eye, k_noise = jax.random.split(key)
        other = redraw(fwd, k_eye)
        psf = other.psf()
        noiseless = other.obs.clip(other.obs.expected(psf))
        photo = other.obs.sample(k_noise, psf)
        out = []
        for target in (photo, noiseless):
            target = target.astype(fn.target.dtype)
            ctx = dataclasses.replace(
                base, target=target, saturated=fwd.obs.saturated_mask(target)
            )
            out.append([v.raw(ctx) if hasattr(v, "raw") else v(ctx) for v in fn.views])
        return out

    return jax.vmap(one)(keys)


def _simulate(
    fn: ResidualFn, latent: Array, n: int, seed: int
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Each view's raw residual (before any scatter's whitening) against at least `n` other
    eyes at `latent` (a whole number of batches), ``(draws, bins)`` per view: against
    their noisy photos, and against their noiseless ones.

    The raw statistics do not depend on a scatter measured before, so one compiled program
    serves the measurement and :func:`scatter_covariance`, whose residuals are whitened by
    it (the simulation of its own that it had took 23-33 s to compile in the bundled
    other-draws fits).
    """
    n = BATCH * math.ceil(n / BATCH)
    keys = jax.random.split(jax.random.key(seed), n)
    bare = fn.unwhitened()
    noisy: list[list[np.ndarray]] = [[] for _ in fn.views]
    clean: list[list[np.ndarray]] = [[] for _ in fn.views]
    for start in range(0, n, BATCH):
        photo_r, clean_r = _draw_batch(bare, latent, keys[start : start + BATCH])
        for v in range(len(fn.views)):
            noisy[v].append(np.asarray(photo_r[v], dtype=np.float64))
            clean[v].append(np.asarray(clean_r[v], dtype=np.float64))
    return [np.concatenate(x) for x in noisy], [np.concatenate(x) for x in clean]


def estimate_scatter(
    fn: ResidualFn, latent: Float[Array, " p"], draws: Mapping[str, int], seed: int = 0
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``{view: (offset, whiten)}`` of the views named in `draws`, at latent `latent`.

    **Arguments:**

    - `fn`: the residual function of a fit (its views and model).
    - `latent`: the point of the parameter space the scatter is measured at.
    - `draws`: ``{view name: number of draws}`` (at least 8 each; the largest is used
      for all, one simulation serving every view).
    - `seed`: of the draws and their noise (a fixed seed: the same fit twice gives the
      same weights).

    **Returns:** per view the offset to subtract from its residual and the whitening
    matrix (module docstring). **Raises:**
    `ConfigError` for a view the fit does not have, fewer than 8 draws, or a model
    without random draws.
    """
    from invglare.errors import ConfigError

    names = list(fn.names)
    for name, n in draws.items():
        if name not in names:
            raise ConfigError(f"draw scatter for view {name!r}, which the fit does not use")
        if int(n) != n or n < 8:
            raise ConfigError(f"view {name!r}: draws must be an integer >= 8, got {n!r}")
    if random_keys(fn.forward.model) == 0:
        raise ConfigError(
            "draws: the model has no random draws (no key), so there is no scatter between "
            "draws to estimate; remove the draws option"
        )
    noisy, clean = _simulate(fn, latent, int(max(draws.values())), seed)
    out = {}
    for v, name in enumerate(names):
        if name not in draws:
            continue
        rp, rc = noisy[v], clean[v]
        cov = _shrunk_covariance(rp) + _shrunk_covariance(rc) / rc.shape[0]
        out[name] = (rc.mean(axis=0), np.linalg.inv(np.linalg.cholesky(cov)))
    return out


def scatter_options(
    fn: ResidualFn,
    latent: Float[Array, " p"],
    view_options: Mapping[str, Mapping[str, Any]] | None,
    seed: int = 0,
) -> dict[str, dict[str, Any]]:
    """`view_options` with the measured scatter added to every view that asks for draws.

    A statistics view with the option ``draws = N`` gets ``offset`` and ``whiten`` (see
    :func:`estimate_scatter`, at `latent`); the other options come back unchanged.
    """
    options = {k: dict(v) for k, v in (view_options or {}).items()}
    draws = {name: int(o["draws"]) for name, o in options.items() if o.get("draws", 0)}
    if not draws:
        return options
    for name, (offset, whiten) in estimate_scatter(fn, latent, draws, seed).items():
        options[name].update(offset=offset, whiten=whiten)
    return options


def scatter_covariance(
    fn: ResidualFn,
    latent: Float[Array, " p"],
    n_draws: int,
    seed: int = 1,
    jacobian: np.ndarray | None = None,
) -> np.ndarray:
    """Covariance of the latent estimate that the scatter between eyes and the noise cause.

    A linearised parametric bootstrap: `n_draws` other eyes at `latent`, each observed
    with noise, give residual vectors ``r_k``; a fit of eye ``k`` would move the estimate
    by ``G (r_k - mean)`` to first order, ``G = (J^T J)^-1 J^T`` with `fn`'s Jacobian at
    `latent` (the trend's, :mod:`invglare.fit.trend_jacobian`, where `fn` differentiates
    so). The covariance of those moves, plus that of the noiseless eyes' over `n_draws`
    (the offsets' uncertainty), is what the estimate scatters by between eyes with the
    same parameters:
    correlations between bins and between views included, whatever the whitening left.
    A `seed` other than the scatter's own keeps the two simulations independent;
    `jacobian`, `fn`'s at `latent` where the caller has it (the fit's solve kept it).

    **Returns:** the ``(p, p)`` covariance of the latent values.
    """
    from invglare.fit.solve import _jacobian_and_residuals

    jac = _jacobian_and_residuals(fn, latent)[0] if jacobian is None else jacobian
    jac = np.asarray(jac, dtype=np.float64)
    noisy, clean = _simulate(fn, latent, int(n_draws), seed)
    n = noisy[0].shape[0]
    gain = np.linalg.pinv(jac)  # (p, n_residuals)
    moves = _residual_vectors(fn, noisy, jac.shape[0]) @ gain.T
    model_moves = _residual_vectors(fn, clean, jac.shape[0]) @ gain.T
    cov = np.atleast_2d(np.cov(moves, rowvar=False))
    return cov + np.atleast_2d(np.cov(model_moves, rowvar=False)) / n


def _residual_vectors(fn: ResidualFn, raw: list[np.ndarray], size: int) -> np.ndarray:
    """`fn`'s residual vectors, ``(draws, size)``, from each view's raw residuals.

    Each view weighted and whitened as `fn` does it; the priors' residuals (a fitted lash
    layout's, the last rows) depend on the parameters alone, the same for every eye, so
    they are left at 0: they move no estimate.
    """
    parts = []
    for view, weight, r in zip(fn.views, fn.weights, raw, strict=True):
        if hasattr(view, "raw"):
            r = np.asarray(jax.vmap(whitened, in_axes=(0, None, None))(r, view.offset, view.whiten))
        parts.append(math.sqrt(weight) * r)
    vectors = np.concatenate(parts, axis=1)
    return np.pad(vectors, ((0, 0), (0, size - vectors.shape[1])))
