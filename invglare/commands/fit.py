"""``invglare fit``: fit a model to a photo and write ``reports/NAME/``.

The config is read and checked by :func:`invglare.config.fit.load_fit` (so
mistakes surface before any compilation), the fit runs in float64 with a
progress bar per discrete choice, and the report is written by
:func:`invglare.fit.report.write_report`, atomically as a whole: an interrupted
run (Ctrl-C) leaves no half-written report and keeps the previous one.

**Example:**

```bash
invglare fit fits/eye_daylight.toml            # -> reports/eye_daylight/
invglare fit fits/camera_cross_screen.toml --out-dir /tmp/cam --n-starts 5
```
"""

from __future__ import annotations

import functools
import logging
import math
import re
import time
from pathlib import Path
from typing import Any

log = logging.getLogger("invglare")


class _Progress:
    """A tqdm bar fed by :class:`~invglare.fit.FitProgress` reports (from JAX's callback thread).

    The bar starts with the first accepted step, so its rate is the solve's, not the compile's.
    """

    def __init__(self, label: str, enabled: bool = True):
        self.label = label
        self.enabled = enabled
        self.bar = None
        self.best: dict[int, float] = {}
        self.stage = -1

    def __call__(self, p) -> None:
        if self.bar is None:
            from tqdm import tqdm

            self.bar = tqdm(desc=self.label, unit="step", disable=not self.enabled)
        if p.stage != self.stage:
            self.stage = p.stage
            self.best.clear()
        self.best[p.start] = p.loss
        self.bar.update(1)
        where = f"stage {p.stage + 1}/{p.n_stages}, " if p.n_stages > 1 else ""
        self.bar.set_postfix_str(
            f"{where}best loss {min(self.best.values()):.6g} "
            f"({len(self.best)}/{p.n_starts} starts)",
            refresh=False,
        )

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def fit_setup(setup, forward=None, progress=None, *, final=True, resume=None):
    """Fit a :class:`~invglare.config.fit.FitSetup`: its stages in order, then the final fit.

    The first stage starts from `setup.starts`; each later one from the best result of
    the one before. **Returns:** the last stage's :class:`~invglare.fit.FitResult`,
    with the earlier stages' records prepended to its `stages` (each record names its
    views; `origin` indexes the first stage's starts), its `starts` and `best_start`
    those of the first stage, and its step count and timings summed along the way.

    - `forward` defaults to `setup.forward` (pass ``setup.forward_for(choice)`` for a
      discrete choice); `progress` is passed to :func:`invglare.fit.fit`.
    - ``final=False`` runs the stages before the final one only (there must be some);
      pass the result as `resume` to run the final stage from its best values later.
      A sweep over discrete choices uses this to refine only the most promising choice.

    **Example:**

    ```python
    with jax.enable_x64(True):
        setup = load_fit("fits/eye_daylight.toml")
        result = fit_setup(setup)
    ```
    """
    import numpy as np

    from invglare.fit import fit

    forward = setup.forward if forward is None else forward
    kwargs = setup.fit_kwargs()
    kwargs.pop("starts")
    kwargs.pop("n_starts")
    paths = setup.space.paths
    # Early stages only seed the next: no covariance or images (two compilations fewer).
    early = {"coarse_to_fine": (1,), "diagnostics": False}
    pre = [(st.views, {**early, "max_steps": st.max_steps}, st.fixed) for st in setup.stages]
    if resume is None:
        plan = pre + ([(setup.views, {}, ())] if final else [])
        if not plan:
            raise ValueError("final=False needs [[stage]] tables to run")
        starts, scan = np.asarray(setup.starts), None
        if setup.scan:
            show = progress is not None and getattr(progress, "enabled", True)
            starts, scan = _scan(setup, forward, *plan[0][::2], n=starts.shape[0], show=show)
        origin = np.arange(starts.shape[0])  # first-stage start each start descends from
        records: list[dict] = []
        n_steps = 0
        timing = {"compile": 0.0, "solve": 0.0, "total": 0.0}
    else:
        starts = np.asarray([[resume.values[p] for p in paths]])
        origin = np.asarray([resume.best_start])
        records, n_steps, timing = list(resume.stages), resume.n_steps, dict(resume.timing_s)
        scan = None
        plan = [(setup.views, {}, ())]
    for k, (views, overrides, fixed) in enumerate(plan):
        space, template, free_starts, held = _hold(setup.space, forward, starts, fixed)
        result = fit(
            space,
            template,
            setup.target,
            views,
            starts=free_starts,
            n_starts=free_starts.shape[0],
            progress=_numbered(progress, k, len(plan)),
            **{
                **kwargs,
                **overrides,
                "truth": _subset(kwargs["truth"], space.paths),
                "view_options": _subset(setup.view_options, views),
            },
        )
        result.values.update(held)
        for key in timing:
            timing[key] += float(result.timing_s.get(key, 0.0))
        for record in result.stages:
            record = dict(record, views=dict(views))
            record["origin"] = [int(origin[i]) for i in record["origin"]]
            if not records and resume is None and scan is not None:
                record["scan"] = scan
            records.append(record)
        n_steps += result.n_steps
        origin = origin[[result.best_start]]
        if len(plan) > 1 or resume is not None:
            shown = ", ".join(
                f"{p.rsplit('.', 1)[-1]}={result.values[p]:.5g}"
                for p in paths
                if p in {q.path for q in setup.space.parameters}
            )
            log.info(
                "stage %d (%s): loss %.6g, best start %d: %s",
                len(records),
                "+".join(views),
                result.loss,
                int(origin[0]),
                shown,
            )
        if k + 1 < len(plan):
            starts = np.asarray([[result.values[p] for p in paths]])
    result.stages = records
    if resume is None:
        first = np.asarray(setup.starts) if scan is None else np.asarray(scan["starts"])
        result.starts = [dict(zip(paths, map(float, row), strict=True)) for row in first]
    else:
        result.starts = resume.starts
    result.best_start = int(origin[0])
    if len(records) > 1:
        # fit() described only its own stage; say where its start came from.
        result.message = re.sub(
            r"\(best of \d+ starts: start \d+\)",
            f"(stage {len(records)} of {len(records)}; from the best of "
            f"{len(result.starts)} starts, start {result.best_start})",
            result.message,
        )
    result.n_steps = n_steps
    result.timing_s = timing
    return result


def _numbered(progress, k: int, n_plan: int):
    """Report fit `k` of a plan's `n_plan` fits as stages of one run (fits before the last
    have one stage each; the last may have several, coarse to fine)."""
    if progress is None:
        return None
    return lambda p: progress(p._replace(stage=k + p.stage, n_stages=n_plan - 1 + p.n_stages))


def _scan(setup, forward, views, fixed, *, n: int, show: bool = True):
    """Score `setup.scan` points across the bounds by the loss of `views`; keep the best `n`.

    No solving: one compiled loss, evaluated point by point. When the flux is free, each
    point gets the flux that matches the photo's unclipped pixels (the photo's sum, the
    initial guess, misses what the clip cut off, which would swamp the comparison).
    **Returns:** the kept starts ``(n, p)`` and a record of the scan (for the report).
    """
    import jax
    import numpy as np
    from tqdm import tqdm

    from invglare.fit import make_residual_fn

    points = setup.draw_starts(setup.scan)
    space, template, free, _ = _hold(setup.space, forward, points, fixed)
    options = _subset(setup.view_options, views)
    fn = make_residual_fn(space, template, setup.target, views, view_options=options)
    latent = np.asarray(space.to_latent(free))
    flux = space.paths.index("obs.flux") if "obs.flux" in space.paths else None
    log.info("scoring %d points across the bounds by %s", len(points), "+".join(views))
    bar = tqdm(latent, desc="scan", unit="point", disable=not show or len(latent) < 8)
    losses, fluxes = [], []
    with jax.enable_x64(True):
        for z in bar:
            loss, f = _scan_point()(fn, z, flux)
            losses.append(float(loss))
            fluxes.append(float(f))
    losses = np.where(np.isfinite(losses), losses, np.inf)
    if flux is not None:
        col = setup.space.paths.index("obs.flux")
        p = setup.space.all[col]
        points[:, col] = np.clip(fluxes, p.lower + 1e-12 * abs(p.lower) + 1e-300, p.upper * 0.999)
    best = np.argsort(losses, kind="stable")[: min(n, len(points))]
    interest = [p.path for p in setup.space.parameters]
    cols = [setup.space.paths.index(p) for p in interest]
    return points[best], {
        "n_points": len(points),
        "views": dict(views),
        "kept": [int(i) for i in best],
        "losses": [float(v) for v in losses],
        "points": [dict(zip(interest, map(float, row[cols]), strict=True)) for row in points],
        "starts": points[best].tolist(),
    }


@functools.cache
def _scan_point():
    import equinox as eqx
    import jax.numpy as jnp

    @eqx.filter_jit
    def point(fn, z, flux_index):
        """The loss at latent `z`, with the flux matched to the unclipped pixels if free."""
        if flux_index is None:
            return fn.loss(z), jnp.nan
        fwd = fn.forward_at(z)
        obs = fwd.obs
        unit = obs.response * obs.transform_psf(fwd.psf())  # counts per unit flux
        use = ~fn.saturated
        excess = jnp.sum(jnp.where(use, fn.target - obs.response * obs.background, 0.0))
        f = jnp.maximum(excess / jnp.sum(jnp.where(use, unit, 0.0)), 1e-30)
        p = fn.space.all[flux_index]
        z = z.at[flux_index].set(p.to_latent(f))
        return fn.loss(z), f

    return point


def _hold(space, forward, starts, fixed):
    """The space without the `fixed` paths, a template holding them, and the reduced starts.

    The held values are those of the first start (a stage holds nuisances, which every
    start shares, or values that the previous stage's best result fixed).
    """
    if not fixed:
        return space, forward, starts, {}
    from invglare.fit import ParameterSpace

    keep = [i for i, p in enumerate(space.paths) if p not in fixed]
    held = {p: float(starts[0][i]) for i, p in enumerate(space.paths) if p in fixed}
    sub = ParameterSpace(
        [p for p in space.parameters if p.path not in fixed],
        [p for p in space.nuisance if p.path not in fixed],
    )
    return sub, space.apply(forward, starts[0]), starts[:, keep], held


def _subset(table, keys):
    """The entries of `table` whose keys are in `keys` (None when there are none)."""
    return None if table is None else {k: v for k, v in table.items() if k in keys} or None


def _loss_key(result) -> float:
    return result.loss if math.isfinite(result.loss) else math.inf


def _log_result(label: str, result) -> None:
    log.info(
        "%s: loss %.6g, reduced chi2 %.4g, %s (compile %.1f s, solve %.1f s)",
        label,
        result.loss,
        result.reduced_chi2,
        result.message,
        result.timing_s["compile"],
        result.timing_s["solve"],
    )


def _choice_label(choice: dict[str, int]) -> str:
    return ", ".join(f"{k.rsplit('.', 1)[-1]}={v}" for k, v in choice.items())


def _model_sections(setup, result) -> dict[str, tuple[str, list[str], Any]]:
    """Report sections particular to the model: the ghosts of a veiling fit."""
    import jax

    from invglare.models.veiling import VeilingGlare

    if not isinstance(setup.forward.model, VeilingGlare):
        return {}
    from invglare.fit.ghost_report import ghost_section

    with jax.enable_x64(True):
        values = setup.space.values_from(result.values)
        fitted = setup.space.apply(setup.forward, values).model
        truth = setup.truth_model()
        lines, data = ghost_section(fitted, truth)
    return {"ghosts": ("Ghosts", lines, data)}


def run_fit(
    config: Path,
    out_dir: Path | None = None,
    n_starts: int | None = None,
    max_steps: int | None = None,
    progress: bool = True,
) -> Path:
    """Run the fit a config describes and write its report. **Returns:** the report folder."""
    import jax

    from invglare.cie_study.config import is_reference_fit
    from invglare.config.fit import load_fit
    from invglare.files.toml import load_toml
    from invglare.fit.report import ReportInfo, write_report

    if is_reference_fit(load_toml(config)):
        return run_reference_fit(config, out_dir, n_starts, max_steps, progress)
    t0 = time.perf_counter()
    with jax.enable_x64(True):
        setup = load_fit(config, out_dir=out_dir, n_starts=n_starts, max_steps=max_steps)
        log.info(
            "fitting %s: %d free parameters, %d starts, views %s; %s",
            setup.target_path,
            setup.space.size,
            setup.starts.shape[0],
            ", ".join(setup.views),
            "ground truth known" if setup.truth else "no ground truth",
        )
        candidates = setup.candidates()
        # With stages and several discrete choices, only the choice whose early stages
        # end lowest gets the (costlier, pixel-wise) final stage.
        sweep_early = len(candidates) > 1 and bool(setup.stages)
        runs: list[tuple[dict[str, int], Any]] = []
        for k, choice in enumerate(candidates):
            label = "fit" if not choice else f"fit {_choice_label(choice)} ({k + 1}/"
            label += f"{len(candidates)})" if choice else ""
            forward = setup.forward_for(choice)
            log.info("%s: compiling the solve (once per model structure), then solving", label)
            bar = _Progress(label, enabled=progress)
            try:
                result = fit_setup(setup, forward, progress=bar, final=not sweep_early)
            finally:
                bar.close()
            _log_result(label, result)
            runs.append((choice, result))
        if sweep_early:
            choice, early = min(runs, key=lambda r: _loss_key(r[1]))
            label = f"fit {_choice_label(choice)}, final stage"
            bar = _Progress(label, enabled=progress)
            try:
                result = fit_setup(setup, setup.forward_for(choice), progress=bar, resume=early)
            finally:
                bar.close()
            _log_result(label, result)
            final_choice, final_result = choice, result
        else:
            final_choice, final_result = min(runs, key=lambda r: _loss_key(r[1]))

    best_choice, best = final_choice, final_result
    discrete = [
        {
            "choice": choice,
            "loss": res.loss,
            "reduced_chi2": res.reduced_chi2,
            "converged": res.converged,
            "message": res.message,
            "timing_s": res.timing_s,
            "views": res.stages[-1].get("views", setup.views) if res.stages else setup.views,
        }
        for choice, res in runs
        if choice
    ]
    info = ReportInfo(
        name=setup.name,
        target=setup.target,
        pixel_scale_deg=setup.pixel_scale_deg,
        saturation=setup.forward.obs.saturation,
        config_path=setup.config_path,
        target_path=setup.target_path,
        model_path=setup.model_path,
        truth_path=setup.truth_path,
        n_starts=int(setup.starts.shape[0]),
        solver=setup.solver,
        discrete=discrete,
        discrete_truth={d.key: d.truth for d in setup.discrete},
        view_options=setup.view_options,
        sections=_model_sections(setup, best),
    )
    info.wall_s = time.perf_counter() - t0
    folder = write_report(setup.out_dir, best, info)
    if best_choice:
        log.info("best discrete choice: %s", _choice_label(best_choice))
    log.info("%s", best.summary())
    log.info("wrote %s (report.md, params.json, figures) in %.1f s", folder, info.wall_s)
    return folder


def run_reference_fit(
    config: Path,
    out_dir: Path | None = None,
    n_starts: int | None = None,
    max_steps: int | None = None,
    progress: bool = True,
) -> Path:
    """Fit the eye's radial GSF to a reference (``[reference]``); write its report folder."""
    from invglare.cie_study.config import load_reference_fit
    from invglare.cie_study.report import write_gsf_report

    t0 = time.perf_counter()
    ref = load_reference_fit(config, out_dir=out_dir, n_starts=n_starts, max_steps=max_steps)
    setup = ref.setup
    log.info(
        "fitting the eye's GSF to %s over %.3g-%.3g deg in %d annuli, %d start(s); compiling "
        "the model first",
        ref.describe(),
        setup.theta_min_deg,
        setup.max_angle_deg(),
        setup.n_bins,
        setup.n_starts,
    )
    result = ref.run(progress=progress)
    log.info("%s", result.summary())
    folder = write_gsf_report(
        result, ref.out_dir, reference=ref.describe(), config_path=ref.config_path
    )
    log.info("wrote %s (report.md, fit.json, gsf.png) in %.1f s", folder, time.perf_counter() - t0)
    return folder
