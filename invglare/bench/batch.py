"""The batch benchmark: photos per minute on Dask, 1 worker against 2, and what a task costs.

The bundled population (``fits/eye_population.toml`` on the photos of
``data_synthetic/eye_population/``; the first `n_photos` of them) is fitted on
LocalClusters of single-threaded worker processes, as ``invglare fit-batch`` runs it
(:mod:`invglare.fit.batch`, :class:`~invglare.config.photo_fit.PhotoFits`); reports go to a
temporary folder. Every worker first fits one photo untimed (it compiles there), so the
timings are of warm workers, which is what a batch of many photos runs on:

- **throughput**: the wall time of the `n_photos` tasks on 1 and on 2 workers, as photos
  per minute, and their ratio (the speed-up);
- **per-photo overhead**: on the warm single worker, the same photos fitted inside one task
  one after another (``PhotoFits.fit_one``: load, fit, report; what ``invglare fit`` does
  on a warm process) against one task per photo through the scheduler; the difference per
  photo is what Dask adds;
- **vmap**: on the warm single worker, the photos fitted `vmap` at a time in one vmapped
  solve per stage (warmed too) against one at a time, and the largest relative difference
  of a fitted value between the two.

Speed is reported, never asserted; ``load_1m`` says how busy the machine was.
"""

from __future__ import annotations

import datetime as dt
import json
import tempfile
import time
from pathlib import Path
from typing import Any

from invglare.bench.timing import load_1m
from invglare.errors import ConfigError

#: Names of the batch benchmarks (selectable like the fit benchmarks).
BATCH_CASES = ("batch_population",)

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "fits" / "eye_population.toml"
PHOTOS = ROOT / "data_synthetic" / "eye_population"


def _shown(path: Path) -> str:
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)


def _timed_direct(work, jobs: list[Any]) -> list[float]:
    """On a worker: fit each photo in this task, one after another; seconds of each."""
    times = []
    for job in jobs:
        t0 = time.perf_counter()
        outcome = work.fit_one(job)
        times.append(time.perf_counter() - t0)
        if outcome["status"] == "failed":
            raise RuntimeError(f"{job.name}: {outcome['reason']}")
    return times


def _on_each_worker(client, fn, *args, only_first: bool = False) -> list[Any]:
    """Run `fn(*args)` as one task pinned to each worker (or the first); wait for all."""
    workers = sorted(client.scheduler_info()["workers"])[: 1 if only_first else None]
    futures = [
        client.submit(fn, *args, workers=[w], allow_other_workers=False, pure=False)
        for w in workers
    ]
    return client.gather(futures)


def _run(client, work, jobs: list[Any], folder: Path, group: int) -> tuple[float, list[Any]]:
    """Wall seconds of fitting `jobs` as tasks of `group` photos each; the outcomes."""
    from invglare.fit.batch import Task, run_tasks

    tasks = [Task(job.name, folder / job.name, job) for job in jobs]
    groups = [tasks[i : i + group] for i in range(0, len(tasks), group)]
    t0 = time.perf_counter()
    outcomes = run_tasks(client, groups, work, progress=False)
    wall = time.perf_counter() - t0
    bad = [o for o in outcomes if o.status == "failed"]
    if bad:
        raise RuntimeError(f"batch benchmark: {bad[0].name} failed: {bad[0].reason}")
    return wall, outcomes


def _values(folder: Path) -> dict[str, float]:
    return {p: e["value"] for p, e in json.loads((folder / "params.json").read_text())
            ["parameters"].items()}  # fmt: skip


def run_batch_benchmark(
    *,
    n_photos: int = 8,
    workers: tuple[int, ...] = (1, 2),
    vmap: int = 4,
    config_path: str | Path = CONFIG,
    photo_dir: str | Path = PHOTOS,
    cache_dir: str | Path | None = None,
) -> dict[str, Any]:
    """Time the population's fits on warm LocalClusters; return one JSON-ready record.

    **Arguments:** `n_photos` photos (the first of `photo_dir`, sorted) fitted with
    `config_path` on a cluster of each size in `workers`; `vmap` photos per vmapped solve
    in the vmap comparison (on the first cluster; 1 leaves it out). `cache_dir`: the
    workers' persistent compilation cache (default: a new one in a temporary folder).
    The timings do not depend on it: every worker fits a warm-up photo before the clock
    starts.

    **Raises:** `ConfigError` for fewer photos than asked or bad settings; `RuntimeError`
    when a photo's fit fails.
    """
    from invglare.config.batch import read_photos
    from invglare.config.photo_fit import PhotoFits
    from invglare.files.toml import load_toml
    from invglare.fit.batch import dask_client

    if n_photos < 1 or vmap < 1 or not workers or min(workers) < 1:
        raise ConfigError(
            f"batch benchmark: n_photos, vmap and workers must be >= 1, got {n_photos}, "
            f"{vmap}, {workers}"
        )
    config_path, photo_dir = Path(config_path), Path(photo_dir)
    jobs = read_photos([str(photo_dir / "*.exr")])
    if len(jobs) < n_photos + 1:
        raise ConfigError(
            f"batch benchmark: {photo_dir} has {len(jobs)} photos; it needs {n_photos} and one "
            "to warm the workers with"
        )
    warm, jobs = jobs[0], jobs[1 : n_photos + 1]
    tables = load_toml(config_path)
    record: dict[str, Any] = {
        "case": BATCH_CASES[0],
        "kind": "batch",
        "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "load_1m_start": load_1m(),
        "config": _shown(config_path),
        "photos": _shown(photo_dir),
        "n_photos": n_photos,
        "clusters": [],
    }
    with tempfile.TemporaryDirectory(prefix="invglare-batch-bench-") as tmp:
        out = Path(tmp)
        cache = out / "jax" if cache_dir is None else Path(cache_dir)
        for n in workers:
            with dask_client(None, n, cache_dir=cache) as client:
                work = PhotoFits(config_path, tables, out / f"w{n}")
                _on_each_worker(client, work, [warm])  # compiles on every worker
                wall, _ = _run(client, work, jobs, out / f"w{n}", 1)
                entry: dict[str, Any] = {
                    "workers": n,
                    "wall_s": wall,
                    "photos_per_min": 60.0 * n_photos / wall,
                    "load_1m": load_1m(),
                }
                if n == workers[0]:
                    direct = PhotoFits(config_path, tables, out / "direct")
                    (times,) = _on_each_worker(client, _timed_direct, direct, jobs,
                                               only_first=True)  # fmt: skip
                    entry["direct_s_per_photo"] = sum(times) / len(times)
                    entry["task_s_per_photo"] = wall / n_photos * n
                    entry["overhead_s_per_photo"] = (
                        entry["task_s_per_photo"] - entry["direct_s_per_photo"]
                    )
                    if vmap > 1:
                        entry.update(_vmap_entry(client, config_path, tables, jobs, out, vmap, n))
                record["clusters"].append(entry)
    base = record["clusters"][0]
    for entry in record["clusters"]:
        entry["speedup"] = entry["photos_per_min"] / base["photos_per_min"]
    record["load_1m_end"] = load_1m()
    return record


def _vmap_entry(client, config_path, tables, jobs, out: Path, vmap: int, n: int) -> dict:
    from invglare.config.photo_fit import PhotoFits

    work = PhotoFits(config_path, tables, out / "vmap")
    _on_each_worker(client, work, jobs[:vmap])  # compiles the vmapped programs on each
    wall, _ = _run(client, work, jobs, out / "vmap", vmap)
    diff = 0.0
    for job in jobs:
        one, many = _values(out / f"w{n}" / job.name), _values(out / "vmap" / job.name)
        for path, value in one.items():
            diff = max(diff, abs(many[path] - value) / max(abs(value), 1e-300))
    return {
        "vmap": vmap,
        "vmap_s_per_photo": wall / len(jobs) * n,
        "vmap_max_rel_diff": diff,
    }


def batch_markdown(record: dict[str, Any]) -> list[str]:
    """The batch benchmark's section of bench.md."""
    lines = [
        f"## Batch fits on Dask: {record['case']}",
        "",
        f"Measured {record['date']}: {record['n_photos']} photos of `{record['photos']}` "
        f"fitted with `{record['config']}` on LocalClusters of single-threaded worker "
        "processes, each pinned to a core of its own (`invglare.fit.batch.pin_to_core`), "
        "every worker warmed first by one untimed fit (it compiles there). Load "
        f"(1 min) {record['load_1m_start']} at the start, {record['load_1m_end']} at the end.",
        "",
        "| workers | wall s | photos per minute | speed-up | load |",
        "|---:|---:|---:|---:|---:|",
    ]
    for c in record["clusters"]:
        lines.append(
            f"| {c['workers']} | {c['wall_s']:.1f} | {c['photos_per_min']:.2f} | "
            f"{c['speedup']:.2f} | {c['load_1m']} |"
        )
    first = record["clusters"][0]
    if "overhead_s_per_photo" in first:
        lines += [
            "",
            f"Per photo on a warm worker: {first['direct_s_per_photo']:.2f} s fitted in one "
            f"task one after another (load, fit, report: `invglare fit`'s work), "
            f"{first['task_s_per_photo']:.2f} s as one task each through the scheduler: "
            f"{first['overhead_s_per_photo']:+.2f} s of overhead per photo.",
        ]
    if "vmap_s_per_photo" in first:
        ratio = first["vmap_s_per_photo"] / first["task_s_per_photo"]
        lines += [
            "",
            f"`--vmap {first['vmap']}` on the warm worker: {first['vmap_s_per_photo']:.2f} s per "
            f"photo against {first['task_s_per_photo']:.2f} s one at a time ({ratio:.2f}x); "
            f"fitted values differ by at most {first['vmap_max_rel_diff']:.1e} (relative).",
        ]
    return lines


__all__ = ["BATCH_CASES", "batch_markdown", "run_batch_benchmark"]
