"""One photo fitted end to end from its checked setup, and the work of a batch's tasks.

:func:`fit_and_report` is what ``invglare fit`` does once its config is loaded: every
discrete choice is fitted (:func:`fit_choices`), the best one reported in
``setup.out_dir`` (:func:`write_fit_report`). :class:`PhotoFits` runs the same for each
photo of a batch on a Dask worker (``invglare fit-batch``, :mod:`invglare.fit.batch`), or
fits several photos of one size in one vmapped solve per stage.

**Example:**

```python
with jax.enable_x64(True):
    setup = load_fit("fits/eye_daylight.toml")
folder, best = fit_and_report(setup)
```
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

log = logging.getLogger("invglare")

#: ``run(forward, label, **kwargs) -> FitResult``: one fit of a setup (kwargs of
#: :meth:`~invglare.config.fit.FitSetup.fit`); the command wraps it in progress bars.
RunFit = Callable[..., Any]


def fit_choices(setup, run: RunFit | None = None) -> tuple[dict[str, int], Any, list[dict]]:
    """Fit `setup` for every discrete choice (one fit when it has none).

    With stages and several choices, only the choice whose early stages end lowest gets
    the (costlier, pixel-wise) final stage. `run` does each fit (default
    ``setup.fit(forward, **kwargs)``). Call it in float64 (``jax.enable_x64(True)``).

    **Returns:** ``(best choice, its FitResult, one record per choice for the report)``.
    """
    if run is None:

        def run(forward, label, **kwargs):
            return setup.fit(forward, **kwargs)

    candidates = setup.candidates()
    sweep_early = len(candidates) > 1 and bool(setup.stages)
    runs: list[tuple[dict[str, int], Any]] = []
    for k, choice in enumerate(candidates):
        label = "fit" if not choice else f"fit {choice_label(choice)} ({k + 1}/"
        label += f"{len(candidates)})" if choice else ""
        runs.append((choice, run(setup.forward_for(choice), label, final=not sweep_early)))
    if sweep_early:
        choice, early = min(runs, key=lambda r: _loss_key(r[1]))
        label = f"fit {choice_label(choice)}, final stage"
        best_choice, best = choice, run(setup.forward_for(choice), label, resume=early)
    else:
        best_choice, best = min(runs, key=lambda r: _loss_key(r[1]))
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
    return best_choice, best, discrete


def fit_and_report(
    setup, run: RunFit | None = None, *, started: float | None = None
) -> tuple[Path, Any]:
    """Fit a loaded :class:`~invglare.config.fit.FitSetup` (every discrete choice) and write
    its report to ``setup.out_dir``, as ``invglare fit`` does.

    `run`: as for :func:`fit_choices`; `started`: the ``time.perf_counter()`` the run
    began at (its wall time goes into the report; default now).

    **Returns:** ``(report folder, the best FitResult)``.
    """
    import jax

    t0 = time.perf_counter() if started is None else started
    with jax.enable_x64(True):
        best_choice, best, discrete = fit_choices(setup, run)
    folder = write_fit_report(setup, best, discrete=discrete, wall_s=time.perf_counter() - t0)
    if best_choice:
        log.info("best discrete choice: %s", choice_label(best_choice))
    return folder, best


def write_fit_report(setup, result, *, discrete: list | None = None, wall_s: float) -> Path:
    """Write the report of `setup`'s fit `result` to ``setup.out_dir`` (atomically, as a
    whole); `wall_s`: the run's wall time so far. **Returns:** the folder."""
    from invglare.fit.report import ReportInfo, write_report

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
        discrete=list(discrete or []),
        discrete_truth={d.path: d.truth for d in setup.discrete},
        view_options=setup.view_options,
        sections=model_sections(setup, result),
    )
    info.wall_s = wall_s
    return write_report(setup.out_dir, result, info)


def model_sections(setup, result) -> dict[str, tuple[str, list[str], Any]]:
    """Report sections particular to the model's kind (e.g. the ghosts of a veiling fit)."""
    import jax

    from invglare.config.model import kind_of

    kind = kind_of(setup.forward.model)
    if kind.report is None:
        return {}
    with jax.enable_x64(True):
        values = setup.space.values_from(result.values)
        fitted = setup.space.apply(setup.forward, values).model
        return kind.report(fitted, setup.truth_model())


def choice_label(choice: dict[str, int]) -> str:
    return ", ".join(f"{k.rsplit('.', 1)[-1]}={v}" for k, v in choice.items())


def _loss_key(result) -> float:
    return result.loss if math.isfinite(result.loss) else math.inf


# --------------------------------------------------------------------------------------
# a batch's tasks


@dataclasses.dataclass(frozen=True)
class PhotoFits:
    """The work of a batch's tasks, run on the workers (picklable): fit each photo of a
    group (:class:`~invglare.config.batch.PhotoJob` s), write its report, and say how it
    went (``{"status", "reason"}`` per photo).

    A photo's own errors (unreadable, refused, a fit that raised) become its outcome; the
    other photos are not affected. A group of several photos of one size is fitted in one
    vmapped solve per stage (:func:`invglare.fit.stages.fit_staged_many`).
    """

    config_path: Path
    config: dict[str, Any]
    batch_dir: Path
    n_starts: int | None = None
    max_steps: int | None = None

    def __call__(self, jobs: list[Any]) -> list[dict[str, str]]:
        if len(jobs) == 1:
            return [self.fit_one(jobs[0])]
        return self.fit_group(jobs)

    def load(self, job: Any):
        """The photo's :class:`~invglare.config.fit.FitSetup` (in float64)."""
        import jax

        from invglare.config.batch import photo_config
        from invglare.config.fit import load_fit

        with jax.enable_x64(True):
            return load_fit(
                self.config_path,
                config=photo_config(self.config, job),
                out_dir=self.batch_dir / job.name,
                n_starts=self.n_starts,
                max_steps=self.max_steps,
            )

    def fit_one(self, job: Any) -> dict[str, str]:
        """Fit one photo as ``invglare fit`` would and write its report."""
        t0 = time.perf_counter()
        try:
            _, best = fit_and_report(self.load(job), started=t0)
        except Exception as err:
            return _failure(job, err)
        return _status(best)

    def fit_group(self, jobs: list[Any]) -> list[dict[str, str]]:
        """Fit photos of one size in one vmapped solve per stage; the others one by one."""
        import jax

        from invglare.errors import ConfigError
        from invglare.fit.stages import fit_staged_many

        t0 = time.perf_counter()
        outcomes: dict[str, dict[str, str]] = {}
        setups = {}
        for job in jobs:
            try:
                setups[job.name] = self.load(job)
            except Exception as err:
                outcomes[job.name] = _failure(job, err)
        by_shape: dict[tuple, list[Any]] = {}
        for job in jobs:
            if job.name in setups:
                by_shape.setdefault(tuple(setups[job.name].target.shape), []).append(job)
        for group in by_shape.values():
            chosen = [setups[j.name] for j in group]
            if len(group) == 1 or chosen[0].discrete:
                for job in group:
                    outcomes[job.name] = self.fit_one(job)
                continue
            try:
                with jax.enable_x64(True):
                    results = fit_staged_many(
                        [_photo_args(s) for s in chosen],
                        stages=chosen[0].stages,
                        view_options=chosen[0].view_options,
                        **chosen[0].solver,
                    )
            except ConfigError as err:  # different structures after all: one by one
                log.info("%d photos not vmapped together (%s): fitted apart", len(group), err)
                for job in group:
                    outcomes[job.name] = self.fit_one(job)
                continue
            except Exception as err:
                for job in group:
                    outcomes[job.name] = _failure(job, err)
                continue
            wall = (time.perf_counter() - t0) / len(jobs)
            for job, setup, result in zip(group, chosen, results, strict=True):
                try:
                    write_fit_report(setup, result, wall_s=wall)
                    outcomes[job.name] = _status(result)
                except Exception as err:
                    outcomes[job.name] = _failure(job, err)
        return [outcomes[job.name] for job in jobs]


def _photo_args(setup) -> dict[str, Any]:
    """The per-photo arguments of :func:`invglare.fit.stages.fit_staged_many` for a setup,
    as :meth:`~invglare.config.fit.FitSetup.fit` passes them to ``fit_staged``."""
    return {
        "space": setup.space,
        "forward": setup.forward,
        "target": setup.target,
        "views": setup.views,
        "starts": setup.starts,
        "scan_points": setup.draw_starts(setup.scan) if setup.scan else None,
        "truth": setup.truth,
    }


def _status(result) -> dict[str, str]:
    from invglare.fit.batch_table import status_of

    status, reason = status_of(result)
    return {"status": status, "reason": reason}


def _failure(job: Any, err: BaseException) -> dict[str, str]:
    from invglare.errors import InvglareError

    if isinstance(err, InvglareError):
        return {"status": "failed", "reason": str(err)}
    # Not a user's mistake: keep the traceback in the worker's log.
    log.error("fitting %s failed:\n%s", job.path, traceback.format_exc())
    return {"status": "failed", "reason": f"{type(err).__name__}: {err}"}
