"""``invglare fit-batch``: one fit config, many photos, fitted on a Dask cluster.

The photos (globs, folders, files or a photo table, :mod:`invglare.config.batch`) are
checked first, and the config with the first photo (so that a mistake in the config
is one error, not one per photo); then each photo becomes a task on a Dask cluster
(:mod:`invglare.fit.batch`): a ``LocalCluster`` of one single-threaded worker process
per core by default, or the cluster at ``--scheduler``. Each photo's report goes to
``runs/NAME/batch/PHOTO/``, as ``invglare fit`` writes one (``NAME`` and ``runs/NAME``
as there: ``fit.name``, ``fit.out_dir`` or ``--out-dir``); the batch table and the
population figures to ``runs/NAME/batch/`` (:mod:`invglare.fit.batch_table`,
:mod:`invglare.fit.batch_figures`). A rerun skips the photos that have a report.

With ``--vmap K``, up to K consecutive photos of one size are fitted by one task in one
vmapped solve per stage (:func:`invglare.fit.stages.fit_staged_many`).

**Example:**

```bash
invglare fit-batch fits/eye_population.toml "data_synthetic/eye_population/*.exr"
invglare fit-batch fits/eye_daylight.toml photos.csv --scheduler tcp://10.0.0.5:8786
```
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

log = logging.getLogger("invglare")


@dataclasses.dataclass(frozen=True)
class BatchSummary:
    """What ``invglare fit-batch`` did: the batch folder, its rows, and this run's counts."""

    folder: Path
    rows: list[Any]
    fitted: int
    skipped: int
    wall_s: float

    @property
    def failures(self) -> list[Any]:
        return [r for r in self.rows if r.failed]


def run_fit_batch(
    config: Path,
    photos: Sequence[str],
    *,
    out_dir: Path | None = None,
    scheduler: str | None = None,
    workers: int | None = None,
    vmap: int = 1,
    n_starts: int | None = None,
    max_steps: int | None = None,
    resume: bool = True,
    progress: bool = True,
    cache_dir: Path | None = None,
) -> BatchSummary:
    """Fit every photo with one config on Dask; write the reports and the batch table.

    **Arguments:** `config`, the fit config; `photos`, as on the command line
    (:func:`invglare.config.batch.read_photos`); `out_dir`, the fit's report folder
    (default as ``invglare fit``: ``fit.out_dir`` or ``runs/NAME``), whose ``batch/``
    receives the batch; `scheduler`, a running Dask scheduler's address (default: a
    LocalCluster of `workers` processes, default one per core); `vmap`, photos per
    vmapped solve; `n_starts`, `max_steps`, as for ``invglare fit``; `resume`, skip
    photos with a report (False refits them); `cache_dir`, JAX's persistent compilation
    cache on the workers (default ``~/.cache/invglare/jax``).

    **Returns:** a :class:`BatchSummary` (failures are in its rows, not raised).

    **Raises:** :class:`~invglare.errors.ConfigError` (before any fit) for bad options,
    photos that cannot be found, a bad config, or a scheduler that cannot be reached.
    """
    from invglare.commands import options
    from invglare.commands.fit import precheck_fit_config
    from invglare.config.batch import read_photos
    from invglare.config.fit import is_reference_fit, read_fit_section
    from invglare.errors import ConfigError
    from invglare.files.atomic import folder_lock
    from invglare.files.outputs import output_folder

    t0 = time.perf_counter()
    options.count(vmap, "--vmap")
    options.count(workers, "--workers")
    options.count(n_starts, "--n-starts")
    options.count(max_steps, "--max-steps")
    if out_dir is not None:
        output_folder(out_dir, "--out-dir")
    config = Path(config)
    tables = precheck_fit_config(config)  # before JAX loads (seconds)
    if is_reference_fit(tables):
        raise ConfigError(
            f"{config} fits a reference glare function, not photos; use invglare fit"
        )
    from invglare.fit import batch as engine

    if scheduler is not None:
        engine.check_address(scheduler)
        if workers is not None:
            raise ConfigError("--workers starts a local cluster; with --scheduler, start workers "
                              "with `dask worker ADDRESS`")  # fmt: skip
    jobs = read_photos(photos)
    name, root = read_fit_section(tables, config, out_dir)
    batch_dir = root / "batch"
    option = "--out-dir" if out_dir is not None else "fit.out_dir"
    output_folder(batch_dir, option)
    cache = engine.DEFAULT_CACHE_DIR if cache_dir is None else cache_dir
    # One run per batch folder (a second would fit the same photos twice), until its table
    # is written.
    with folder_lock(batch_dir, option=option):
        return _run_locked(config, tables, jobs, name, batch_dir, scheduler, workers, vmap,
                           n_starts, max_steps, resume, progress, cache, t0)  # fmt: skip


def _run_locked(
    config, tables, jobs, name, batch_dir, scheduler, workers, vmap, n_starts, max_steps,
    resume, progress, cache, t0,
) -> BatchSummary:  # fmt: skip
    """The batch, its folder's lock held: the fits, then the table and figures."""
    from invglare.config.photo_fit import PhotoFits
    from invglare.fit import batch as engine
    from invglare.fit.batch_figures import population_figures
    from invglare.fit.batch_table import collect_rows, write_table

    with contextlib.ExitStack() as stack:
        client = None
        if scheduler is not None:  # reached, or refused, within seconds: before other work
            client = stack.enter_context(engine.dask_client(scheduler, cache_dir=cache))
        _check_config(config, tables, jobs, batch_dir, vmap)
        tasks = [engine.Task(job.name, batch_dir / job.name, job) for job in jobs]
        engine.recover_unfinished([t.folder for t in tasks])  # before asking what is done
        done = [t for t in tasks if resume and engine.finished(t.folder) is not None]
        todo = [t for t in tasks if t not in done]
        log.info(
            "%d photos: %d to fit, %d finished before (skipped)%s",
            len(tasks), len(todo), len(done), "" if resume else "; --no-resume refits them",
        )  # fmt: skip
        outcomes = []
        where = ""
        if todo:
            if client is None:
                client = stack.enter_context(engine.dask_client(None, workers, cache_dir=cache))
            n_workers = len(client.scheduler_info().get("workers", {}))
            where = (f"the Dask cluster at {scheduler}" if scheduler else "a LocalCluster") + (
                f" of {n_workers} worker(s)"
            )
            log.info("fitting %d photos on %s%s", len(todo), where,
                     f", up to {vmap} per vmapped solve" if vmap > 1 else "")  # fmt: skip
            groups = [todo[i : i + vmap] for i in range(0, len(todo), vmap)]
            work = PhotoFits(config, tables, batch_dir, n_starts, max_steps)
            outcomes = engine.run_tasks(client, groups, work, progress=progress,
                                        skipped=len(done))  # fmt: skip
    shown = {job.name: _shown(job.path) for job in jobs}
    rows = collect_rows(tasks, outcomes, shown)
    wall = time.perf_counter() - t0
    table = batch_dir / "batch.md"
    if todo or not table.is_file():
        figures = population_figures(batch_dir, rows)
        notes = [f"fit config `{_shown(config)}`; reports in `{_shown(batch_dir)}/PHOTO/`"]
        if todo:
            notes.append(
                f"this run fitted {len(todo)} photo(s) on {where} in {wall:.0f} s"
                + (f", up to {vmap} per vmapped solve" if vmap > 1 else "")
                + (f"; {len(done)} were finished before" if done else "")
            )
        write_table(batch_dir, rows, title=name, figures=figures, notes=notes)
    summary = BatchSummary(batch_dir, rows, len(todo), len(done), wall)
    log.info(
        "wrote %s and batch.csv: %d ok, %d failed or not converged, in %.1f s",
        table, len(rows) - len(summary.failures), len(summary.failures), wall,
    )  # fmt: skip
    return summary


def _check_config(
    config: Path, tables: dict[str, Any], jobs: Sequence[Any], batch_dir: Path, vmap: int
) -> None:
    """Load the config with the first photo that loads: a config mistake is one error
    here, not one per photo on the workers. Photos that cannot be read are left to their
    tasks (they fail there, with their reason, and the others go on)."""
    import jax

    from invglare.config.batch import photo_config
    from invglare.config.fit import load_fit
    from invglare.errors import ConfigError, InputDataError

    for job in jobs:
        try:
            with jax.enable_x64(True):
                setup = load_fit(config, config=photo_config(tables, job),
                                 out_dir=batch_dir / job.name)  # fmt: skip
        except InputDataError:
            continue
        if vmap > 1 and setup.discrete:
            raise ConfigError(
                f"--vmap {vmap}: {config} sweeps [[discrete]] choices, which change the model's "
                "structure; fit it without --vmap"
            )
        return


def _shown(path: Path) -> str:
    try:
        return os.path.relpath(Path(path).resolve(), Path.cwd())
    except ValueError:
        return str(path)
