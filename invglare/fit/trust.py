"""When to distrust a fit: flags for the report and ``params.json``.

:func:`fit_flags` turns a fit's numbers into a list of flags, each a plain dict
``{"kind", "message", ...}`` (``"path"`` for a parameter's flag, plus the numbers it rests
on), in this order:

| kind               | raised when                                                             |
|--------------------|-------------------------------------------------------------------------|
| `not_at_optimum`   | a few Fisher-scoring steps of the exact log-likelihood from the result  |
|                    | gain more than ``d / 2`` (d free parameters), or the gradient's length  |
|                    | in standard-error units (the Newton decrement) exceeds 1                |
| `reduced_chi2`     | the reduced χ² of a noise-normalised objective is off 1 by more than 5 |
|                    | of its own standard deviations and 5 %; the message names a likely     |
|                    | cause: structure the model cannot draw (a few pixels carry the excess, |
|                    | or the residuals are spatially correlated), or a wrong noise model     |
|                    | (white residuals: which of gain and read noise, from where the excess  |
|                    | is)                                                                    |
| `truth_beyond_3se` | a known truth lies more than 3 standard errors from the value          |
| `at_bound`         | a value within 1 % of the bounds' width of a bound (one-sided bounds:  |
|                    | within 1 % of its distance from the initial value)                     |
| `stderr_undefined` | a parameter's standard error is undefined (not constrained)            |

:func:`optimum_check` is the local check behind `not_at_optimum`; it is given the
likelihood's scoring-form Jacobian (``J^T r`` the gradient of ``-log L``, ``J^T J`` the
Fisher information, see :func:`invglare.fit.views.pixel_residuals`) and the deviance as
functions of the latent vector, so that it reuses the fit's compiled programs.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

#: A value is "at" a bound within this fraction of the bounds' width.
BOUND_FRACTION = 0.01
#: Standard errors beyond which a known truth is flagged.
TRUTH_SIGMAS = 3.0
#: A reduced chi-square is flagged off 1 by more than this many of its standard deviations
#: (sqrt(2 / dof)) and by more than `CHI2_RELATIVE`.
CHI2_SIGMAS = 5.0
CHI2_RELATIVE = 0.05
#: Newton decrement (the gradient's length in standard-error units) above which a result is
#: not at the likelihood's optimum.
MAX_DECREMENT = 1.0
#: Block size (px) of the residual-structure test, and the variance ratio of block means
#: above which residuals count as spatially structured (white noise gives about 1).
STRUCTURE_BLOCK = 4
STRUCTURE_RATIO = 2.0
#: Bins of expected counts, and the ratio of the chi-square to what a per-bin rescaled noise
#: model gives, above which a few pixels carry the misfit (see :func:`misfit_tail`).
LEVEL_BINS = 4
MISFIT_TAIL = 1.5
CHI2_1_MEDIAN = 0.454936


def optimum_check(
    information: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    deviance: Callable[[np.ndarray], float],
    latent: np.ndarray,
    inside: Callable[[np.ndarray], bool],
    *,
    steps: int = 3,
) -> dict[str, Any]:
    """A few Fisher-scoring steps of the exact log-likelihood from `latent`.

    **Arguments:**

    - `information`: ``z -> (J, r)``, the scoring form (``J^T r = -grad log L``,
      ``J^T J`` the Fisher information).
    - `deviance`: ``z -> sum of squared deviance residuals`` (``-2 log L`` + a constant).
    - `latent`: where the fit ended.
    - `inside`: ``z -> bool``, whether a latent point keeps every bound.
    - `steps`: scoring steps at most (each halved up to 5 times until it gains).

    **Returns:** ``{"gain": log L gained, "decrement": sqrt(g^T F^-1 g) at the result,
    "steps": steps taken, "latent": the best point}``; NaN where the information is singular.
    """
    z = np.asarray(latent, dtype=np.float64)
    dev = float(deviance(z))
    dev0 = dev
    decrement = math.nan
    taken = 0
    for k in range(steps):
        jac, r = (np.asarray(a, dtype=np.float64) for a in information(z))
        grad = jac.T @ r
        fisher = jac.T @ jac
        try:
            step = -np.linalg.solve(fisher, grad)
        except np.linalg.LinAlgError:
            break
        if not np.all(np.isfinite(step)):
            break
        if k == 0:
            decrement = math.sqrt(max(float(-grad @ step), 0.0))
        for _ in range(6):
            trial = z + step
            if inside(trial):
                d_trial = float(deviance(trial))
                if math.isfinite(d_trial) and d_trial < dev:
                    z, dev = trial, d_trial
                    taken += 1
                    break
            step = step / 2
        else:
            break
    return {"gain": (dev0 - dev) / 2.0, "decrement": decrement, "steps": taken, "latent": z}


def residual_structure(residual_map: np.ndarray, used: np.ndarray) -> float:
    """Variance of `STRUCTURE_BLOCK`² block means times the block's pixel count, over the
    variance of the residuals: about 1 for white noise, large for residuals with structure."""
    k = STRUCTURE_BLOCK
    r = np.where(used, residual_map, 0.0)
    h, w = (s // k * k for s in r.shape)
    if h == 0 or w == 0:
        return math.nan
    blocks = r[:h, :w].reshape(h // k, k, w // k, k)
    counts = used[:h, :w].reshape(h // k, k, w // k, k).sum(axis=(1, 3))
    full = counts == k * k
    var = float(np.var(r[used])) if used.any() else math.nan
    if full.sum() < 4 or not var > 0:
        return math.nan
    means = blocks.sum(axis=(1, 3))[full] / (k * k)
    return float(np.var(means) * k * k / var)


def misfit_tail(residual_map: np.ndarray, expected: np.ndarray, used: np.ndarray) -> float:
    """How much of the chi-square a per-level rescaling of the noise cannot explain.

    The pixels are split into `LEVEL_BINS` bins of expected counts; within a bin, residuals
    whose noise is merely mis-scaled are Gaussian with one variance ``k``, estimated robustly
    as ``median(r**2) / 0.455`` (the median of a chi-square of one degree of freedom). The
    ratio of the summed squared residuals to the summed ``n_bin * k_bin`` is about 1 then,
    and large when a few pixels carry the misfit (a core or streak the model draws wrong).
    """
    r2 = residual_map[used] ** 2
    e = expected[used]
    if r2.size < 10 * LEVEL_BINS:
        return math.nan
    edges = np.quantile(e, np.linspace(0.0, 1.0, LEVEL_BINS + 1)[1:-1])
    which = np.searchsorted(edges, e)
    scaled = sum(
        (which == b).sum() * np.median(r2[which == b]) / CHI2_1_MEDIAN
        for b in range(LEVEL_BINS)
        if (which == b).any()
    )
    return float(r2.sum() / scaled) if scaled > 0 else math.nan


def chi2_cause(
    reduced_chi2: float,
    residual_map: np.ndarray,
    expected: np.ndarray,
    used: np.ndarray,
    gain: float,
    read_noise: float,
) -> tuple[str, str]:
    """A likely cause of a reduced chi-square far from 1: ``(cause, explanation)``."""
    if reduced_chi2 < 1.0:
        return "noise_overestimated", (
            "the residuals are smaller than the noise model says: the gain (electrons per "
            "count) is set too low or the read noise too high, or the photo was smoothed or "
            "resampled (neighbouring pixels are no longer independent)"
        )
    structure = residual_structure(residual_map, used)
    tail = misfit_tail(residual_map, expected, used)
    model = (
        "structure the model cannot draw (a component missing or drawn differently, e.g. "
        "lashes or particles where the model has other ones, a core resampled too coarsely), "
        "a local minimum, or a source that is not a point"
    )
    if math.isfinite(tail) and tail > MISFIT_TAIL:
        return "model_misfit", (
            f"a few pixels carry the misfit (the squared residuals sum to {tail:.3g}× what a "
            f"rescaled noise model would give at their levels): {model}"
        )
    if math.isfinite(structure) and structure > STRUCTURE_RATIO:
        return "model_misfit", (
            f"the residuals have spatial structure ({STRUCTURE_BLOCK}×{STRUCTURE_BLOCK}-px block "
            f"means carry {structure:.3g}× the variance white noise gives them): {model}"
        )
    shot = (np.maximum(expected, 0.0) / gain > read_noise**2) & used
    dark = used & ~shot
    r2 = residual_map**2
    m_shot = float(r2[shot].mean()) if shot.sum() > 10 else math.nan
    m_dark = float(r2[dark].mean()) if dark.sum() > 10 else math.nan
    if math.isfinite(m_shot) and (not math.isfinite(m_dark) or m_shot > m_dark):
        return "noise_gain", (
            "the residuals are white but larger than the noise model says, most where the "
            f"photon noise dominates (mean squared residual {m_shot:.3g} there, "
            f"{m_dark:.3g} where the read noise does): the gain (electrons per count) is "
            "probably set too high"
        )
    return "noise_read", (
        "the residuals are white but larger than the noise model says, most where the read "
        f"noise dominates (mean squared residual {m_dark:.3g} there, {m_shot:.3g} where "
        "the photon noise does): the read noise is probably set too low"
    )


def fit_flags(
    *,
    paths: list[str],
    values: Mapping[str, float],
    stderr: Mapping[str, float],
    bounds: Mapping[str, tuple[float, float, float]],
    truth: Mapping[str, float] | None,
    reduced_chi2: float,
    dof: int,
    normalised: bool,
    optimum: Mapping[str, Any] | None,
    likelihood_pure: bool,
    residual_map: np.ndarray | None = None,
    expected: np.ndarray | None = None,
    used: np.ndarray | None = None,
    gain: float = 1.0,
    read_noise: float = 0.0,
) -> list[dict[str, Any]]:
    """The flags of a fit (module docstring), most serious first.

    `bounds`: ``{path: (lower, upper, initial value)}``; `normalised`: whether the loss is
    a chi-square (noise-normalised residuals); `optimum`: :func:`optimum_check`'s record
    (None: not run); `likelihood_pure`: whether the fit's objective was the likelihood
    alone; `residual_map`, `expected`, `used`: ``(target - expected) / sigma``, the mean
    counts and the pixels in the likelihood (for the chi-square's cause).
    """
    flags: list[dict[str, Any]] = []
    d = len(paths)
    if optimum is not None:
        gain_l, dec = float(optimum["gain"]), float(optimum["decrement"])
        if gain_l > d / 2 or (math.isfinite(dec) and dec > MAX_DECREMENT):
            why = (
                "the fit's own objective was not the likelihood alone, so its optimum is not "
                "the likelihood's"
                if not likelihood_pure
                else "the solver stopped short of the optimum (raise max_steps, tighten rtol)"
            )
            flags.append(
                {
                    "kind": "not_at_optimum",
                    "gain": gain_l,
                    "decrement": dec,
                    "message": f"not at the likelihood's optimum: {optimum['steps']} scoring "
                    f"steps from the result gain {gain_l:.3g} in log-likelihood (more than "
                    f"d/2 = {d / 2:g} is significant) and the gradient is {dec:.3g} standard "
                    f"errors long; {why}",
                }
            )
    if normalised and dof > 0 and math.isfinite(reduced_chi2):
        off = abs(reduced_chi2 - 1.0)
        if off > CHI2_SIGMAS * math.sqrt(2.0 / dof) and off > CHI2_RELATIVE:
            cause, text = "unknown", "no residual map to name a cause"
            if residual_map is not None and expected is not None and used is not None:
                cause, text = chi2_cause(
                    reduced_chi2, residual_map, expected, used, gain, read_noise
                )
            flags.append(
                {
                    "kind": "reduced_chi2",
                    "value": reduced_chi2,
                    "cause": cause,
                    "message": f"reduced χ² = {reduced_chi2:.4g}, not about 1 "
                    f"(±{math.sqrt(2.0 / dof):.2g}): {text}; the standard errors assume the "
                    "model and the noise model are right",
                }
            )
    return flags + parameter_flags(paths, values, stderr, bounds, truth)


def parameter_flags(
    paths: Sequence[str],
    values: Mapping[str, float],
    stderr: Mapping[str, float],
    bounds: Mapping[str, tuple[float, float, float]],
    truth: Mapping[str, float] | None,
) -> list[dict[str, Any]]:
    """The flags of single parameters (`truth_beyond_3se`, `at_bound`, `stderr_undefined`):
    :func:`fit_flags`'s last part, rerun when a fit's standard errors are replaced."""
    flags: list[dict[str, Any]] = []
    for p in paths:
        v, e = float(values[p]), float(stderr[p])
        if truth and p in truth:
            t = float(truth[p])
            if math.isfinite(e) and e > 0 and abs(v - t) > TRUTH_SIGMAS * e:
                flags.append(
                    {
                        "kind": "truth_beyond_3se",
                        "path": p,
                        "z": (v - t) / e,
                        "message": f"{p}: the truth {t:.6g} is {(v - t) / e:+.3g} standard "
                        f"errors from the value {v:.6g}",
                    }
                )
        lo, hi, init = bounds[p]
        for bound, side in ((lo, "lower"), (hi, "upper")):
            if not math.isfinite(bound):
                continue
            other = hi if side == "lower" else lo
            scale = (other - bound) if math.isfinite(other) else (init - bound)
            if abs(v - bound) <= BOUND_FRACTION * abs(scale):
                flags.append(
                    {
                        "kind": "at_bound",
                        "path": p,
                        "bound": bound,
                        "message": f"{p} = {v:.6g} is at its {side} bound {bound:g}: the "
                        "optimum may lie beyond it, and its standard error means little",
                    }
                )
        if not (math.isfinite(e) and e >= 0):
            flags.append(
                {
                    "kind": "stderr_undefined",
                    "path": p,
                    "message": f"{p}: standard error undefined (the data do not constrain it, "
                    "or it is degenerate with another parameter)",
                }
            )
    return flags


def flags_summary(flags: Sequence[Mapping[str, Any]]) -> str:
    """The tail a fit's message gets for its flags: how many, and the first (most serious)
    one's message; empty when there are none."""
    if not flags:
        return ""
    return f"; {len(flags)} flag{'s' if len(flags) > 1 else ''}: {flags[0]['message']}"


#: Said by results written before flags existed when a converged fit's residuals were far
#: above the noise; :func:`poor_fit` still reads it.
LEGACY_POOR_FIT = "the model does not explain the photo"


def poor_fit(flags: Sequence[Mapping[str, Any]], message: str = "") -> bool:
    """Whether a fit's `flags` say the model does not explain the photo: a `reduced_chi2`
    flag above 1 (residuals far above the noise), or, for a result written before flags
    existed, its `message` saying so."""
    above = any(f.get("kind") == "reduced_chi2" and f.get("value", 0.0) > 1.0 for f in flags)
    return above or LEGACY_POOR_FIT in message
