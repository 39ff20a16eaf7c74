"""The sampling benchmark: one emcee step of the daylight-eye posterior, batched or not.

The posterior of the bundled daylight-eye fit (``fits/eye_daylight.toml`` on its 256²
photo, 7 free parameters, the Poisson–Gaussian pixel likelihood of
:func:`invglare.fit.sample.make_log_posterior`), sampled by ``emcee.EnsembleSampler``
with 32 walkers from a ball around the committed fit, in the same process:

- **vectorize on**: emcee hands all walkers of a half-step to
  :class:`~invglare.fit.sample.BatchedLogProb` at once (``vectorize=True``), which
  evaluates them in compiled, vmapped batches of a given size (all 16, 8, 4 or 1);
- **vectorize off**: emcee calls a jitted one-walker log-probability once per walker.

Reported per mode: milliseconds per emcee step (the median over timed steps, after a
warm-up step that compiles), and effective samples per second, ``walkers / (tau_max ·
seconds per step)``, with ``tau_max`` the largest integrated autocorrelation time of the
committed chain (``reports/eye_daylight/posterior/summary.json``) when there is one: a
few timed steps cannot estimate tau, and tau does not depend on how fast a step runs.

Where one walker's time goes (:func:`walker_parts`): the log-probability of one walker at
the fit, and its parts compiled and timed on their own, calls alternating — the model's
PSF, the observation (sub-pixel shift, flux, background) and the pixel likelihood.
"""

from __future__ import annotations

import datetime as dt
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from invglare.bench.timing import load_1m
from invglare.errors import ConfigError

#: Names of the sampling benchmarks (selectable like the fit benchmarks).
SAMPLE_CASES = ("sample_daylight_eye",)

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "fits" / "eye_daylight.toml"
WALKERS = 32
#: Batch sizes of the vectorized mode (emcee evaluates half the walkers per call).
BATCHES = (16, 8, 4, 1)
#: Alternating timed calls of each part of a walker's evaluation.
PART_REPEATS = 30


def _shown(path: Path) -> str:
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)


def _tau_max(summary: Path) -> tuple[float | None, dict[str, Any] | None]:
    if not summary.is_file():
        return None, None
    data = json.loads(summary.read_text())
    taus = [p.get("tau") for p in data.get("parameters", {}).values()]
    taus = [t for t in taus if isinstance(t, int | float) and math.isfinite(t)]
    info = {k: data.get(k) for k in ("n_walkers", "n_steps", "converged", "moves")}
    return (max(taus) if taus else None), info


def _time_steps(sampler, start: np.ndarray, n_steps: int) -> list[float]:
    """Seconds of each of `n_steps` emcee steps after one warm-up step (compilation)."""
    state = sampler.run_mcmc(start, 1, progress=False)
    times = []
    for _ in range(n_steps):
        t0 = time.perf_counter()
        state = sampler.run_mcmc(state, 1, progress=False)
        times.append(time.perf_counter() - t0)
    return times


def walker_parts(lp: Any, latent: Any, repeats: int = PART_REPEATS) -> list[dict[str, Any]]:
    """Milliseconds of one walker's log-probability at `latent` and of each of its parts.

    Each part is compiled on its own and the calls alternate, so that the machine's load
    falls on all alike. XLA fuses across the parts inside the whole walker, so the parts
    need not add up to it exactly. Pixel likelihoods only (a views posterior has no
    observation step): ``[]`` otherwise.
    """
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    if lp.likelihood != "pixels":
        return []
    z = jnp.asarray(latent)
    fwd = lp.space.apply(lp.forward, lp.space.from_latent(z))
    model = eqx.filter_jit(lambda f: f.model())
    observe = eqx.filter_jit(lambda o, p: o.expected(p))

    @eqx.filter_jit
    def likelihood(post, e):
        return post.forward.obs.log_likelihood(
            post.target, e, censoring=post.censoring, mask=post.mask, censored=post.censored
        )

    # The compiling calls also give each part its input.
    psf = jax.block_until_ready(model(fwd))
    expected = jax.block_until_ready(observe(fwd.obs, psf))
    whole = eqx.filter_jit(lambda post, x: post(x))
    jax.block_until_ready((likelihood(lp, expected), whole(lp, z)))
    parts = {
        "model PSF": (model, (fwd,)),
        "observation (shift, flux, background)": (observe, (fwd.obs, psf)),
        "pixel likelihood": (likelihood, (lp, expected)),
        "whole walker (log-probability)": (whole, (lp, z)),
    }
    times: dict[str, list[float]] = {name: [] for name in parts}
    for _ in range(repeats):
        for name, (f, args) in parts.items():
            t0 = time.perf_counter()
            jax.block_until_ready(f(*args))
            times[name].append(time.perf_counter() - t0)
    whole_ms = float(np.median(times["whole walker (log-probability)"]))
    return [
        {
            "part": name,
            "ms": 1e3 * float(np.median(t)),
            "min_ms": 1e3 * float(np.min(t)),
            "share": float(np.median(t)) / whole_ms,
        }
        for name, t in times.items()
    ]


def run_sample_benchmark(
    *,
    n_steps: int = 5,
    config_path: str | Path = CONFIG,
    batches: tuple[int, ...] = BATCHES,
    vectorize_off: bool = True,
) -> dict[str, Any]:
    """Time emcee steps of the daylight-eye posterior; return one JSON-ready record.

    **Arguments:** `n_steps` timed steps per mode (after one warm-up); `config_path`,
    the fit whose stored ``params.json`` (and ``posterior/summary.json``, if any) lies
    in its report folder (:func:`~invglare.config.fit.stored_fit`: a fresh run's, else the
    committed one); `batches`, the batch sizes of the vectorized mode;
    `vectorize_off`, also time emcee's per-walker calls.

    **Raises:** `ConfigError` when the fit has no ``params.json`` (run ``invglare fit``).
    """
    import emcee
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from invglare.config.fit import load_fit, stored_fit
    from invglare.fit import FitResult
    from invglare.fit.sample import BatchedLogProb, initial_walkers, make_log_posterior

    if int(n_steps) != n_steps or n_steps < 1:
        raise ConfigError(f"sample benchmark n_steps must be an integer >= 1, got {n_steps!r}")
    config_path = Path(config_path).resolve()
    with jax.enable_x64(True):
        setup = load_fit(config_path)
        params = stored_fit(setup)
        if not params.is_file():
            raise ConfigError(
                f"the sampling benchmark starts from the fit in {params}, which does not "
                f"exist: run invglare fit {config_path} first"
            )
        fit_result = FitResult.from_json(params)
        lp = make_log_posterior(setup.space, setup.forward, setup.target)
        tau_max, chain = _tau_max(params.parent / "posterior" / "summary.json")
        record: dict[str, Any] = {
            "case": "sample_daylight_eye",
            "kind": "sample",
            "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
            "load_1m_start": load_1m(),
            "config": _shown(config_path),
            "photo": list(setup.target.shape),
            "n_parameters": setup.space.size,
            "n_walkers": WALKERS,
            "n_timed_steps": int(n_steps),
            "tau_max": tau_max,
            "tau_from": chain,
            "modes": [],
        }
        start = initial_walkers(
            setup.space, fit_result, WALKERS, log_prob=BatchedLogProb(lp, WALKERS), seed=0
        )

        def add(mode: str, batch: int | None, times: list[float], compile_s: float) -> None:
            step_ms = 1e3 * float(np.median(times))
            ess = WALKERS / (tau_max * step_ms / 1e3) if tau_max else None
            record["modes"].append(
                {
                    "mode": mode,
                    "batch_size": batch,
                    "step_ms": step_ms,
                    "min_step_ms": 1e3 * float(np.min(times)),
                    "walker_eval_ms": step_ms / WALKERS,
                    "first_step_s": compile_s,
                    "effective_samples_per_s": ess,
                }
            )

        for b in batches:
            f = BatchedLogProb(lp, int(b))
            sampler = emcee.EnsembleSampler(WALKERS, setup.space.size, f, vectorize=True)
            t0 = time.perf_counter()
            times = _time_steps(sampler, start, n_steps)
            first = time.perf_counter() - t0 - sum(times)
            add("vectorize on", int(b), times, first)

        if vectorize_off:
            one = eqx.filter_jit(lambda post, z: post(z))

            def single(z: np.ndarray) -> float:
                value = float(one(lp, jnp.asarray(z, dtype=jnp.float64)))
                return value if math.isfinite(value) else -math.inf

            sampler = emcee.EnsembleSampler(WALKERS, setup.space.size, single)
            t0 = time.perf_counter()
            times = _time_steps(sampler, start, n_steps)
            add("vectorize off", None, times, time.perf_counter() - t0 - sum(times))
        record["walker_parts"] = walker_parts(lp, setup.space.to_latent(fit_result.values))
    record["load_1m_end"] = load_1m()
    return record


def sample_markdown(record: dict[str, Any]) -> list[str]:
    """The sampling benchmark's section of bench.md."""
    tau = record.get("tau_max")
    chain = record.get("tau_from") or {}
    tau_text = (
        f"tau_max = {tau:.1f} steps, from the committed chain ({chain.get('n_walkers')} walkers "
        f"x {chain.get('n_steps')} steps)"
        if tau
        else "no committed chain, so no tau and no effective samples"
    )
    ny, nx = record["photo"]
    lines = [
        f"## Sampling: {record['case']} ({nx}x{ny} photo)",
        "",
        f"Measured {record['date']}: emcee with {record['n_walkers']} walkers on the "
        f"{record['n_parameters']}-parameter posterior of the fit `{record['config']}`; the "
        f"median of {record['n_timed_steps']} steps after a warm-up step. {tau_text}; "
        "effective samples per second = walkers / (tau_max x seconds per step). Load (1 min) "
        f"{record['load_1m_start']} at the start, {record['load_1m_end']} at the end.",
        "",
        "| mode | batch | ms per step | ms per walker | first step s | effective samples/s |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for m in record["modes"]:
        ess = m["effective_samples_per_s"]
        lines.append(
            f"| {m['mode']} | {m['batch_size'] or '—'} | {m['step_ms']:.0f} | "
            f"{m['walker_eval_ms']:.1f} | {m['first_step_s']:.1f} | "
            f"{'—' if ess is None else format(ess, '.3g')} |"
        )
    parts = record.get("walker_parts") or []
    if parts:
        lines += [
            "",
            "Where one walker's time goes, at the fit: each part compiled on its own, "
            f"{PART_REPEATS} calls each, alternating (the whole walker fuses across parts, so "
            "they need not add up to it).",
            "",
            "| part | median ms | min ms | share of the walker |",
            "|---|---:|---:|---:|",
        ]
        lines += [
            f"| {p['part']} | {p['ms']:.2f} | {p['min_ms']:.2f} | {p['share']:.0%} |" for p in parts
        ]
    return lines


__all__ = ["SAMPLE_CASES", "run_sample_benchmark", "sample_markdown", "walker_parts"]
