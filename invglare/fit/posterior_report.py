"""The posterior report of a sampled fit: summary table, corner and trace plots, predictive band.

:func:`write_posterior_report` writes, atomically, into one folder
(``reports/NAME/posterior/`` for ``invglare sample``):

| file             | content                                                              |
|------------------|----------------------------------------------------------------------|
| `summary.md`     | table: median, 16/84 and 2.5/97.5 percentiles, τ, truth; settings     |
| `summary.json`   | the same numbers, the correlation matrix and every run's settings     |
| `corner.png`     | pairwise marginals (the `corner` package), truth lines where known    |
| `trace.png`      | every walker's path per parameter and the log-probability, burn-in    |
| `predictive.png` | posterior-predictive band of the radial profile against the target   |

The posterior-predictive band draws `n_predictive` parameter vectors from the
chain (after burn-in) and, for each, the model's radial profile (the band of
the model: parameter uncertainty only) and the profile of a noisy photo drawn
from the observation model's noise (parameter and photon / read noise, in the
Gaussian approximation the likelihood uses: where the target's profile should
lie).

**Example:**

```python
post = sample(space, forward, photo, fit_result, "reports/disk/posterior/chain.h5")
write_posterior_report(post, "reports/disk/posterior", space=space,
                       forward_template=forward, target=photo, name="disk")
```
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from invglare.errors import ConfigError
from invglare.files.atomic import atomic_path, write_json_atomic, write_text_atomic
from invglare.fit.observation import Forward
from invglare.fit.params import ParameterSpace
from invglare.fit.result import _clean  # the one JSON cleaning: arrays to lists, NaN to null
from invglare.fit.sample import SampleResult
from invglare.fit.views import radial_bin_radii, radial_profile

__all__ = ["posterior_predictive_profiles", "summary_dict", "write_posterior_report"]

FORMAT = "invglare.posterior"
VERSION = 1


def _label(path: str) -> str:
    # "model.aperture.pupil.diameter_mm" is long for an axis: the last two parts name it.
    return ".".join(path.split(".")[-2:])


def summary_dict(result: SampleResult, name: str | None = None) -> dict[str, Any]:
    """The report's numbers as a JSON-ready dict (the layout of ``summary.json``)."""
    pc = result.percentiles()
    ess = result.effective_samples()
    params = {}
    for p in result.paths:
        entry: dict[str, Any] = dict(pc[p])
        entry["tau"] = result.tau[p]
        entry["steps_over_tau"] = result.n_steps / result.tau[p] if result.tau[p] > 0 else None
        entry["effective_samples"] = ess[p]
        entry["nuisance"] = p in result.nuisance
        if p in result.fit_values:
            entry["fit_value"] = result.fit_values[p]
            entry["fit_stderr"] = result.fit_stderr.get(p)
        if result.truth and p in result.truth:
            t = result.truth[p]
            entry["truth"] = t
            entry["truth_in_68"] = bool(pc[p]["p16"] <= t <= pc[p]["p84"])
            entry["truth_in_95"] = bool(pc[p]["p2_5"] <= t <= pc[p]["p97_5"])
        params[p] = entry
    return _clean(
        {
            "format": FORMAT,
            "version": VERSION,
            "name": name,
            "chain_file": None if result.path is None else result.path.name,
            "sampling_space": result.sampling_space,
            "likelihood": result.likelihood,
            "n_walkers": result.n_walkers,
            "n_steps": result.n_steps,
            "burn_in": result.burn_in,
            "thin": result.thin,
            "n_samples": int(result.samples().shape[0]),
            "converged": result.converged,
            "tau_factor": result.tau_factor,
            "acceptance_fraction": {
                "mean": float(np.mean(result.acceptance)),
                "min": float(np.min(result.acceptance)),
                "max": float(np.max(result.acceptance)),
            },
            "moves": [[m, w] for m, w in result.moves],
            "parameters": params,
            "correlation": {"paths": result.paths, "matrix": result.correlation()},
            "warnings": list(result.warnings),
            "timing": dict(result.timing),
            "runs": list(result.runs),
        }
    )


def _fmt(v: float | None, digits: int = 5) -> str:
    if v is None or not math.isfinite(v):
        return "–"
    return f"{v:.{digits}g}"


def digits_to_resolve(centre: float, low: float, high: float, at_least: int = 5) -> int:
    """Significant digits that show `low` and `high` around `centre` apart: two digits of
    their difference (a lash count of 37.00001 with a 68 % interval 2e-4 wide is
    37.000012, 36.99990, ..., not 37 | 37 | 37)."""
    width = abs(high - low)
    if not all(map(math.isfinite, (centre, width))) or width == 0 or centre == 0:
        return at_least
    return max(at_least, math.ceil(math.log10(abs(centre) / width)) + 2)


def _markdown(summary: dict[str, Any], files: dict[str, str]) -> str:
    name = summary["name"] or "posterior"
    acc = summary["acceptance_fraction"]
    moves = ", ".join(f"{m} ({w:.2g})" for m, w in summary["moves"])
    lines = [
        f"# Posterior of {name}",
        "",
        f"emcee, {summary['n_walkers']} walkers x {summary['n_steps']} steps "
        f"(burn-in {summary['burn_in']}, thinned by {summary['thin']}: "
        f"{summary['n_samples']} samples); moves: {moves}; sampled in the "
        f"{summary['sampling_space']} space with the {summary['likelihood']} likelihood; "
        f"acceptance {acc['mean']:.3f} (walkers {acc['min']:.3f}-{acc['max']:.3f}); "
        + (
            f"**converged** (chain > {summary['tau_factor']:g} τ for every parameter)."
            if summary["converged"]
            else f"**not converged** (chain < {summary['tau_factor']:g} τ): see the warnings."
        ),
        "",
        "| parameter | median | 16% | 84% | 2.5% | 97.5% | τ (steps) | N/τ | fit | truth |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for p, e in summary["parameters"].items():
        label = f"{p} (nuisance)" if e["nuisance"] else p
        n = digits_to_resolve(e["median"], e["p16"], e["p84"])
        fit = (
            f"{_fmt(e.get('fit_value'), n)} ± {_fmt(e.get('fit_stderr'), 3)}"
            if "fit_value" in e
            else "–"
        )
        truth = _fmt(e.get("truth"), n)
        if "truth" in e:
            truth += " (in 95%)" if e["truth_in_95"] else " (**outside 95%**)"
        lines.append(
            f"| `{label}` | {_fmt(e['median'], n)} | {_fmt(e['p16'], n)} | {_fmt(e['p84'], n)} | "
            f"{_fmt(e['p2_5'], n)} | {_fmt(e['p97_5'], n)} | {_fmt(e['tau'], 3)} | "
            f"{_fmt(e['steps_over_tau'], 3)} | {fit} | {truth} |"
        )
    corr = np.asarray(summary["correlation"]["matrix"], dtype=float)
    paths = summary["correlation"]["paths"]
    strong = [
        (paths[i], paths[j], corr[i, j])
        for i in range(len(paths))
        for j in range(i + 1, len(paths))
        if abs(corr[i, j]) >= 0.5
    ]
    if strong:
        lines += ["", "Strongly correlated pairs (|ρ| ≥ 0.5):", ""]
        lines += [f"- `{a}` – `{b}`: ρ = {r:+.2f}" for a, b, r in strong]
    if summary["warnings"]:
        lines += ["", "## Warnings", ""]
        lines += [f"- {w}" for w in summary["warnings"]]
    timing = summary.get("timing") or {}
    if timing:
        lines += [
            "",
            "## Timing",
            "",
            f"- last run: {_fmt(timing.get('total_s'), 3)} s, "
            f"{_fmt(1e3 * (timing.get('s_per_step') or math.nan), 3)} ms per step, "
            f"{_fmt(1e3 * (timing.get('s_per_walker_eval') or math.nan), 3)} ms per walker "
            f"evaluation (batches of {timing.get('batch_size', '?')}); setup (compilation, "
            f"batch tuning, starting walkers) {_fmt(timing.get('setup_s'), 3)} s",
        ]
    if summary["runs"]:
        lines += ["", "## Runs", ""]
        for r in summary["runs"]:
            mv = ", ".join(f"{m} ({w:.2g})" for m, w in r.get("moves", []))
            lines.append(
                f"- from step {r.get('start_step')}: {r.get('n_steps')} steps, moves {mv}, "
                f"batch size {r.get('batch_size')}, stopped: {r.get('stopped')}"
            )
    pred = summary.get("predictive")
    if pred:
        lines += [
            "",
            f"Posterior predictive ({pred['n_draws']} draws with photon and read noise): "
            f"{100 * pred['fraction_of_rings_inside_95']:.0f}% of the target's 1-px rings lie "
            "inside the 95% band (about 95% expected when the model fits).",
        ]
    lines += ["", "## Figures", ""]
    for title, f in files.items():
        lines += [f"### {title}", "", f"![{title}]({f})", ""]
    return "\n".join(lines).rstrip() + "\n"


# --------------------------------------------------------------------------------------
# posterior predictive


def _profiles(space, forward, n_bins, r_max, x, key):
    fwd = space.apply(forward, x)
    expected, predicted = fwd.predict()
    h, w = predicted.shape
    centre = (w // 2 + fwd.obs.dx_px, h // 2 + fwd.obs.dy_px)
    # The Gaussian approximation of the Poisson–Gaussian noise: the one the likelihood
    # uses, and far cheaper to compile than jax.random.poisson's rejection loop.
    sigma = jnp.sqrt(fwd.obs.variance(expected))
    noisy = fwd.obs.clip(expected + sigma * jax.random.normal(key, expected.shape, expected.dtype))
    return (
        radial_profile(predicted, centre, n_bins, r_max),
        radial_profile(noisy, centre, n_bins, r_max),
    )


def posterior_predictive_profiles(
    result: SampleResult,
    space: ParameterSpace,
    forward_template: Forward,
    target: Float[ArrayLike, "h w"],
    *,
    n_predictive: int = 64,
    seed: int = 0,
    batch_size: int = 8,
) -> dict[str, np.ndarray]:
    """Radial profiles of the model and of noisy photos for posterior draws, and of the target.

    **Returns:** ``{"radius_px": (n_bins,), "model": (n, n_bins), "noisy": (n,
    n_bins), "target": (n_bins,)}``; 1-px rings out to ``min(h, w) // 2 - 1``,
    centred on each draw's source position (the target's on the posterior
    median's).
    """
    if list(result.paths) != list(space.paths):
        raise ConfigError(
            f"the chain is for {result.paths} but the space frees {list(space.paths)}"
        )
    flat = result.samples()
    rng = np.random.default_rng(seed)
    idx = rng.choice(flat.shape[0], size=min(int(n_predictive), flat.shape[0]), replace=False)
    xs = flat[idx]
    tgt = np.asarray(target, dtype=float)
    h, w = tgt.shape
    r_max = float(min(h, w) // 2 - 1)
    n_bins = int(r_max)
    with jax.enable_x64(True):
        # One compiled program for everything: run eagerly, each small op compiles alone.
        @eqx.filter_jit
        def run(fwd, xs, key, x_median, tgt):
            keys = jax.random.split(key, xs.shape[0])
            model, noisy = jax.lax.map(
                lambda a: _profiles(space, fwd, n_bins, r_max, a[0], a[1]),
                (xs, keys),
                batch_size=batch_size,
            )
            med = space.apply(fwd, x_median)
            centre = (w // 2 + med.obs.dx_px, h // 2 + med.obs.dy_px)
            return model, noisy, radial_profile(tgt, centre, n_bins, r_max)

        model, noisy, target_profile = run(
            forward_template,
            jnp.asarray(xs),
            jax.random.key(seed),
            jnp.asarray(np.median(flat, axis=0)),
            jnp.asarray(tgt),
        )
    return {
        "radius_px": radial_bin_radii(n_bins, r_max),
        "model": np.asarray(model),
        "noisy": np.asarray(noisy),
        "target": np.asarray(target_profile),
    }


# --------------------------------------------------------------------------------------
# figures


def _save(fig, path: Path) -> None:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90)


def _corner_figure(result: SampleResult):
    import corner
    from matplotlib.figure import Figure

    p = len(result.paths)
    fig = Figure(figsize=(2.2 * p + 1, 2.2 * p + 1))
    truths = None
    if result.truth:
        truths = [result.truth.get(q) for q in result.paths]
    corner.corner(
        result.samples(),
        labels=[_label(q) for q in result.paths],
        truths=truths,
        truth_color="tab:red",
        quantiles=[0.025, 0.16, 0.5, 0.84, 0.975],
        title_quantiles=[0.16, 0.5, 0.84],
        show_titles=True,
        title_fmt=".4g",
        title_kwargs={"fontsize": 8},
        label_kwargs={"fontsize": 8},
        fig=fig,
    )
    return fig


def _trace_figure(result: SampleResult):
    from matplotlib.figure import Figure

    p = len(result.paths)
    fig = Figure(figsize=(9, 1.7 * (p + 1)), layout="constrained")
    axes = fig.subplots(p + 1, 1, sharex=True)
    steps = np.arange(result.n_steps)
    alpha = max(0.05, min(0.4, 8.0 / result.n_walkers))
    for i, q in enumerate(result.paths):
        ax = axes[i]
        ax.plot(steps, result.chain[:, :, i], color="k", alpha=alpha, lw=0.5)
        if result.truth and q in result.truth:
            ax.axhline(result.truth[q], color="tab:red", lw=1)
        ax.set_ylabel(_label(q), fontsize=7)
        ax.axvline(result.burn_in, color="tab:blue", ls="--", lw=1)
    lp = np.where(np.isfinite(result.log_prob), result.log_prob, np.nan)
    # Relative to the best value (the absolute one is ~-1e5 and varies in its last digits),
    # scaled to the samples after burn-in, not to the first steps far below them.
    top = np.nanmax(lp)
    rel = lp - top
    axes[-1].plot(steps, rel, color="k", alpha=alpha, lw=0.5)
    low = np.nanpercentile(rel[result.burn_in :], 1) if result.burn_in < len(rel) else -10.0
    low = min(low, -2.0 * len(result.paths))
    axes[-1].set_ylim(1.3 * low, 0.1 * abs(low))
    axes[-1].set_ylabel("log prob - max", fontsize=7)
    axes[-1].axvline(result.burn_in, color="tab:blue", ls="--", lw=1, label="burn-in")
    axes[-1].set_xlabel("step")
    axes[-1].legend(fontsize=7, loc="lower right")
    return fig


def _predictive_figure(pp: dict[str, np.ndarray]):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 6), layout="constrained")
    ax, ax2 = fig.subplots(2, 1, sharex=True, height_ratios=(3, 1.3))
    r = pp["radius_px"]
    noisy = np.percentile(pp["noisy"], [2.5, 16, 50, 84, 97.5], axis=0)
    model = np.percentile(pp["model"], [2.5, 50, 97.5], axis=0)
    ax.fill_between(r, noisy[0], noisy[4], color="tab:blue", alpha=0.25, label="predictive 95%")
    ax.fill_between(r, noisy[1], noisy[3], color="tab:blue", alpha=0.45, label="predictive 68%")
    # The model band as lines: filled, it would hide the predictive band it lies inside.
    ax.plot(r, model[0], color="tab:orange", lw=0.8, ls="--", label="model 95%")
    ax.plot(r, model[2], color="tab:orange", lw=0.8, ls="--")
    ax.plot(r, model[1], color="tab:orange", lw=1, label="model median")
    ax.plot(r, pp["target"], "k.", ms=3, label="target")
    positive = np.concatenate([pp["target"][pp["target"] > 0], noisy[0][noisy[0] > 0]])
    if positive.size:
        ax.set_yscale("log")
        ax.set_ylim(max(positive.min() * 0.5, noisy[2].max() * 1e-7), None)
    ax.set_ylabel("mean counts per pixel")
    ax.legend(fontsize=8)
    ax.set_title("posterior predictive: radial profile")
    width = np.maximum(noisy[3] - noisy[1], 1e-300) / 2
    ax2.axhspan(-1, 1, color="tab:blue", alpha=0.2)
    ax2.plot(r, (pp["target"] - noisy[2]) / width, "k.", ms=3)
    ax2.axhline(0, color="tab:orange", lw=1)
    ax2.set_ylabel("(target - median)\n/ half 68% width", fontsize=7)
    ax2.set_xlabel("radius (photo pixels)")
    return fig


def write_posterior_report(
    result: SampleResult,
    out_dir: str | os.PathLike[str],
    *,
    space: ParameterSpace | None = None,
    forward_template: Forward | None = None,
    target: Float[ArrayLike, "h w"] | None = None,
    name: str | None = None,
    n_predictive: int = 64,
    seed: int = 0,
) -> dict[str, Path]:
    """Write the posterior report of `result` into `out_dir` (files in the module docstring).

    The posterior-predictive figure needs `space`, `forward_template` and
    `target`; without them it is left out. Every file is written atomically.

    **Returns:** ``{kind: path}`` of the files written (``"markdown"``, ``"json"``,
    ``"corner"``, ``"trace"``, ``"predictive"``).

    **Example:**

    ```python
    write_posterior_report(post, "reports/eye_daylight/posterior", space=space,
                           forward_template=forward, target=photo, name="eye_daylight")
    ```
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written: dict[str, Path] = {}
    figures: dict[str, str] = {}

    fig = _corner_figure(result)
    _save(fig, out / "corner.png")
    written["corner"] = out / "corner.png"
    figures["Corner plot"] = "corner.png"

    fig = _trace_figure(result)
    _save(fig, out / "trace.png")
    written["trace"] = out / "trace.png"
    figures["Traces"] = "trace.png"

    summary = summary_dict(result, name)
    if space is not None and forward_template is not None and target is not None:
        pp = posterior_predictive_profiles(
            result, space, forward_template, target, n_predictive=n_predictive, seed=seed
        )
        _save(_predictive_figure(pp), out / "predictive.png")
        written["predictive"] = out / "predictive.png"
        figures["Posterior predictive radial profile"] = "predictive.png"
        lo, hi = np.percentile(pp["noisy"], [2.5, 97.5], axis=0)
        inside = (pp["target"] >= lo) & (pp["target"] <= hi)
        summary["predictive"] = {
            "n_draws": int(pp["model"].shape[0]),
            "fraction_of_rings_inside_95": float(np.mean(inside)),
            "radius_px": pp["radius_px"].tolist(),
            "target": pp["target"].tolist(),
            "noisy_p2_5": lo.tolist(),
            "noisy_p97_5": hi.tolist(),
        }
        summary = _clean(summary)
    written["json"] = write_json_atomic(out / "summary.json", summary)
    written["markdown"] = write_text_atomic(out / "summary.md", _markdown(summary, figures))
    return written
