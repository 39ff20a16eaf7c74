"""``invglare fit``: fit a model to a photo and write ``runs/NAME/``.

The config is read and checked by :func:`invglare.config.fit.load_fit` (so
mistakes surface before any compilation), the fit (:meth:`FitSetup.fit
<invglare.config.fit.FitSetup.fit>`: scan, stages, final fit, see
:mod:`invglare.fit.stages`) runs in float64 with a progress bar per discrete choice,
and the report is written by :func:`invglare.fit.report.write_report`, atomically as a
whole: an interrupted run (Ctrl-C) leaves no half-written report and keeps the
previous one. This module holds the command only: reading, progress and logging; the
sweep over discrete choices and the report are :func:`invglare.config.photo_fit.fit_and_report`'s
(which ``invglare fit-batch`` runs for each photo on its workers).

**Example:**

```bash
invglare fit fits/eye_daylight.toml            # -> runs/eye_daylight/
invglare fit fits/camera_cross_screen.toml --out-dir /tmp/cam --n-starts 5
```
"""

from __future__ import annotations

import contextlib
import logging
import sys
import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

log = logging.getLogger("invglare")


@contextlib.contextmanager
def logged_deprecations(config: Path) -> Iterator[None]:
    """Log the DeprecationWarnings raised inside (a config's older spellings) as warnings.

    Python hides DeprecationWarnings raised outside ``__main__``; on the command line the
    user who wrote the config must see them. Other warnings pass through unchanged.
    """
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DeprecationWarning)
        yield
    for w in caught:
        if issubclass(w.category, DeprecationWarning):
            log.warning("%s: %s", config, w.message)
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)


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


class _ScanBar:
    """A tqdm bar fed by :class:`~invglare.fit.stages.ScanProgress` reports (scans of 8
    points or more), announced by a log line."""

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self.bar = None

    def __call__(self, p) -> None:
        if p.done == 0:
            from tqdm import tqdm

            log.info("scoring %d points across the bounds by %s", p.total, "+".join(p.views))
            disable = not self.enabled or p.total < 8
            self.bar = tqdm(total=p.total, desc="scan", unit="point", disable=disable)
            return
        self.bar.update(1)
        if p.done == p.total:
            self.bar.close()


def _log_stage(stage) -> None:
    """Log a finished stage of a staged fit (a :class:`~invglare.fit.stages.StageDone`)."""
    shown = ", ".join(f"{p.rsplit('.', 1)[-1]}={v:.5g}" for p, v in stage.values.items())
    log.info(
        "stage %d (%s): loss %.6g, best start %d: %s",
        stage.number,
        "+".join(stage.views),
        stage.loss,
        stage.best_start,
        shown,
    )


def _fit(setup, forward, label: str, progress: bool, **kwargs):
    """`setup.fit(forward, ...)` with a progress bar, logged when done."""
    bar = _Progress(label, enabled=progress)
    try:
        # Without a bar the solves carry no host callback, so JAX's persistent cache
        # (`--cache-dir`) can keep them for the next run.
        result = setup.fit(
            forward, progress=bar if progress else None, scan_progress=_ScanBar(progress),
            stage_done=_log_stage, **kwargs,
        )  # fmt: skip
    finally:
        bar.close()
    log.info(
        "%s: loss %.6g, reduced chi2 %.4g, %s (compile %.1f s, solve %.1f s)",
        label,
        result.loss,
        result.reduced_chi2,
        result.message,
        result.timing_s["compile"],
        result.timing_s["solve"],
    )
    return result


def precheck_fit_config(config: Path) -> dict[str, Any]:
    """The fit config's tables, its TOML and section names checked before JAX loads (which
    takes seconds), so that a typo is reported at once. **Raises:** ConfigError."""
    from invglare.config.fit import SECTIONS, is_reference_fit
    from invglare.config.section import check_sections
    from invglare.files.toml import load_toml

    tables = load_toml(config)
    if not is_reference_fit(tables):  # a reference fit's sections: invglare.cie_study.config
        check_sections(tables, SECTIONS, str(config))
    return tables


def run_fit(
    config: Path,
    out_dir: Path | None = None,
    n_starts: int | None = None,
    max_steps: int | None = None,
    progress: bool | None = None,
) -> Path:
    """Run the fit a config describes and write its report. **Returns:** the report folder.

    `progress`: a progress bar; ``None``: when stderr is a terminal. (A bar is fed by host
    callbacks from the solves, which keeps JAX from caching them on disk.)
    """
    from invglare.commands import options
    from invglare.config.fit import is_reference_fit, load_fit
    from invglare.files.atomic import folder_lock
    from invglare.files.outputs import output_folder

    if progress is None:
        progress = sys.stderr.isatty()

    options.count(n_starts, "--n-starts")
    options.count(max_steps, "--max-steps")
    if out_dir is not None:
        output_folder(out_dir, "--out-dir", replaced=True)
    if is_reference_fit(precheck_fit_config(config)):
        return run_reference_fit(
            config, out_dir=out_dir, n_starts=n_starts, max_steps=max_steps, progress=progress
        )
    import jax

    t0 = time.perf_counter()
    with jax.enable_x64(True), logged_deprecations(config):
        setup = load_fit(config, out_dir=out_dir, n_starts=n_starts, max_steps=max_steps)
    option = "--out-dir" if out_dir is not None else "fit.out_dir"
    output_folder(setup.out_dir, option, replaced=True)
    # One run per report folder, from before the fit until its report is in place.
    with folder_lock(setup.out_dir, option=option):
        return _fit_and_report(setup, t0, progress)


def _fit_and_report(setup, t0: float, progress: bool) -> Path:
    """The fit of a loaded setup, and its report (the folder's lock held)."""
    from invglare.config.photo_fit import fit_and_report

    log.info(
        "fitting %s: %d free parameters, %d starts, views %s; %s",
        setup.target_path,
        setup.space.size,
        setup.starts.shape[0],
        views_in_order(setup.stages, setup.views),
        "ground truth known" if setup.truth else "no ground truth",
    )

    def run(forward, label, **kwargs):
        log.info("%s: compiling the solve (once per model structure), then solving", label)
        return _fit(setup, forward, label, progress, **kwargs)

    folder, best = fit_and_report(setup, run, started=t0)
    log.info("%s", best.summary())
    wall = time.perf_counter() - t0
    log.info("wrote %s (report.md, params.json, figures) in %.1f s", folder, wall)
    return folder


def views_in_order(stages, final_views) -> str:
    """Every stage's views, then the final fit's: ``"radial, angular then pixels"``."""
    return " then ".join(", ".join(v) for v in [*(st.views for st in stages), final_views])


def run_reference_fit(config: Path, *, progress: bool = True, **overrides: Any) -> Path:
    """Fit the eye's radial GSF to a reference (``[reference]``); write its report folder.

    `overrides`: `out_dir`, `n_starts`, `max_steps`, as for :func:`run_fit`.
    """
    from invglare.cie_study.config import load_reference_fit
    from invglare.cie_study.report import write_gsf_report

    t0 = time.perf_counter()
    ref = load_reference_fit(config, **overrides)
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
