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

import math
import os
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import emcee
import numpy as np
from jaxtyping import ArrayLike, Bool, Float

from invglare.errors import ConfigError, InputDataError, NumericalError
from invglare.fit.observation import Forward
from invglare.fit.params import ParameterSpace
from invglare.fit.result import FitResult
from invglare.fit.sample.batching import BatchedLogProb, tune_batch_size
from invglare.fit.sample.chain import (
    CHAIN_GROUP,
    FORMAT,
    RUNNING,
    ChainBackend,
    chain_meta,
    close_killed_runs,
    load_chain,
    read_meta,
    repair_chain,
    stored_iteration,
    write_meta,
)
from invglare.fit.sample.diagnostics import integrated_tau
from invglare.fit.sample.moves import emcee_moves, parse_moves
from invglare.fit.sample.posterior import fingerprint, make_log_posterior
from invglare.fit.sample.result import SampleProgress, SampleResult
from invglare.fit.sample.signals import StopRequests, deferred_signals
from invglare.fit.sample.walkers import check_fit_matches, initial_walkers, spans_all_dimensions


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
    check_fit_matches(space, fit_result)
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
        scatter_at=fit_result.values if likelihood == "views" else None,
    )  # fmt: skip

    stored = stored_iteration(path) if path.is_file() else 0
    if resume:
        if stored == 0:
            raise InputDataError(
                f"there is no chain to resume at {path}"
                + (" (it holds no step)" if path.is_file() else "")
                + "; run without --resume to start one"
            )
        meta = read_meta(path)
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
        meta = chain_meta(space, fit_result, n_walkers, likelihood, fingerprint(lp))

    if batch_size != "auto" and (int(batch_size) != batch_size or batch_size < 1):
        raise ConfigError(f"batch_size must be an integer >= 1 or 'auto', got {batch_size!r}")
    # Until the batch size is tuned, a provisional one (its program is reused if it wins).
    probe = BatchedLogProb(lp, min(8, n_walkers // 2) if batch_size == "auto" else batch_size)

    if resume:
        # The last stored state, with its log-probabilities and random state: the run
        # continues exactly where it stopped (the committed step, whatever a kill left).
        repair_chain(path)
        initial = ChainBackend(str(path), CHAIN_GROUP, read_only=True).get_last_sample()
        tune_walkers = initial.coords
    else:
        initial = initial_walkers(
            space, fit_result, n_walkers, scale=init_scale, seed=seed, force=force,
            log_prob=probe,
        )  # fmt: skip
        if not spans_all_dimensions(initial):
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
    backend = ChainBackend(str(path), name=CHAIN_GROUP)
    if not resume:
        with deferred_signals():
            backend.reset(n_walkers, space.size)
        write_meta(path, meta)
    sampler = emcee.EnsembleSampler(
        n_walkers, space.size, f, moves=emcee_moves(spec), backend=backend, vectorize=True
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
        "stopped": RUNNING,
        "pid": os.getpid(),
    }
    # The record is there before the first step: a killed run leaves it "running", and the
    # next run closes it as killed at the step the counter holds.
    meta = read_meta(path) or meta
    close_killed_runs(meta, run_info["start_step"])
    meta.setdefault("runs", []).append(run_info)
    with deferred_signals():
        write_meta(path, meta)
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

    def record_run() -> None:
        if bar is not None:
            bar.close()
        elapsed = time.perf_counter() - t_start
        # From the counter: the steps this run committed, whatever interrupted it.
        end_step = stored_iteration(path)
        run_info["end_step"] = int(end_step)
        run_info["n_steps"] = int(end_step - run_info["start_step"])
        run_info["stopped"] = reason
        run_info["n_nan"] = int(f.n_nan)
        run_info["timing"] = {
            "total_s": elapsed,
            "s_per_step": elapsed / done_steps if done_steps else math.nan,
            "s_per_walker_eval": f.seconds_per_walker,
            "setup_s": setup_s,
            "batch_size": int(batch_size),
        }
        # The run record is completed even on an interrupt, so the file says what happened.
        current = read_meta(path) or meta
        runs = current.setdefault("runs", [])
        if runs and runs[-1].get("pid") == run_info["pid"] and runs[-1]["stopped"] == RUNNING:
            runs[-1] = run_info
        else:
            runs.append(run_info)
        with deferred_signals():
            write_meta(path, current)

    try:
        with StopRequests() as stop:
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
                tau = integrated_tau(backend.get_chain())
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
    except KeyboardInterrupt:
        # Recorded once this handler is left: a signal landing inside h5py leaves a file
        # id open in the interrupted frames, and HDF5 refuses to reopen that file with
        # other flags while the traceback keeps those frames alive.
        interrupted = True
    except BaseException:
        record_run()
        raise
    else:
        interrupted = False
    record_run()
    if interrupted:
        raise KeyboardInterrupt
    result = load_chain(path, space, tau_factor=tau_factor)
    result.timing = dict(run_info["timing"])
    return result
