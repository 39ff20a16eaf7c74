"""Convergence of a chain: autocorrelation times, burn-in, thinning and warnings in words."""

from __future__ import annotations

import math
import warnings

import emcee
import numpy as np

from invglare.fit.params import ParameterSpace


def integrated_tau(latent: np.ndarray) -> np.ndarray:
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
    tau = integrated_tau(latent)
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
