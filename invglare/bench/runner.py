"""``invglare bench``: time every case at every size, run the fit benchmark, write reports.

Two kinds of record go to ``reports/bench.json`` (``{"meta", "records", "fit"}``) and
``reports/bench.md``:

- **per-size timings** (:data:`invglare.bench.cases.CASES`), each with its ratio to the
  fastest bare FFT of the same size measured in the same run;
- **fit benchmarks** (:data:`invglare.bench.fit.FIT_CASES`), run once (not per size):
  invglare's fit against scipy's finite-difference least squares, side by side; and the
  **sampling benchmark** (:data:`invglare.bench.sample.SAMPLE_CASES`): emcee steps of a
  posterior with batched and per-walker log-probabilities (kept with the fit records); and
  the **batch benchmark** (:data:`invglare.bench.batch.BATCH_CASES`): photos per minute
  of ``invglare fit-batch`` on 1 and 2 Dask workers, a task's overhead, ``--vmap``.

Speed is only ever reported as ratios of times measured in the same run, never asserted.
"""

from __future__ import annotations

import datetime as dt
import gc
import logging
import math
import os
import platform
import time
import traceback
from pathlib import Path
from typing import Any

from tqdm import tqdm

from invglare._core.allocator import retain_freed_memory
from invglare.bench.batch import BATCH_CASES
from invglare.bench.cases import CASES as STATIC_CASES
from invglare.bench.cases import Case
from invglare.bench.fit import FIT_CASES
from invglare.bench.holographic_cases import HOLOGRAPHIC_CASES, paper_markdown
from invglare.bench.peer_cases import PEER_CASES, cpu_info
from invglare.bench.quad_cases import PROGRESSIVE_PAIRS, QUAD_CASES, quad_markdown
from invglare.bench.sample import SAMPLE_CASES
from invglare.bench.temporal_cases import TEMPORAL_CASES, stage_markdown
from invglare.bench.timing import load_1m, measure_together
from invglare.bench.torch_cases import PAIRS, TORCH_CASES, overhead_markdown, passive_openmp
from invglare.bench.unknown_draw import UNKNOWN_DRAW_CASES
from invglare.bench.veiling_cases import VEILING_CASES
from invglare.errors import ConfigError

log = logging.getLogger("invglare")

#: Seconds of timed repeats per case and size, after which timing stops (>= 3 repeats).
BUDGET_S = 20.0

#: Per-size cases that run with every selection, like the floors: the ratios use them.
REFERENCES = ("fft_jax",)
#: Every per-size case: the static models, the temporal model's frame pipeline, the
#: veiling series against the ghost count, the holographic eye against the paper's rows,
#: the torch layer against the same JAX call, and the quad-based transforms against the
#: paper's tables.
CASES: tuple[Case, ...] = (
    *STATIC_CASES,
    *TEMPORAL_CASES,
    *VEILING_CASES,
    *HOLOGRAPHIC_CASES,
    *TORCH_CASES,
    *QUAD_CASES,
)

#: Header notes of bench.md (also in bench.json's meta).
NOTES = (
    "JAX's CPU FFT (ducc, in XLA's thread pool) uses both cores here, as the scipy and "
    "pyfftw floors do (see the `cpu/wall` of the `fft_jax` rows); the floor is the faster "
    "library at each size, and `vs jax fft` compares each case with JAX's own bare FFT of "
    "the same size.",
    "The machine is shared: `load` is the 1-minute load average when the case was timed "
    "(2 cores; above 2, other processes competed for them) and `cpu/wall` the process's CPU "
    "time over wall time while timing (below 1: the case waited for a core). Ratios compare "
    "times taken in the same run, so load affects both sides, but not necessarily equally.",
    "`first call s` is the first call of the case: tracing, XLA compilation and one run.",
    "glibc's malloc keeps freed memory for reuse (`invglare._core.allocator.retain_freed_memory`, "
    "as the `invglare` command sets it; `retain_freed_memory` in bench.json's meta says "
    "whether it took effect): otherwise XLA's per-call buffers are mapped and zeroed anew "
    "by the kernel on every call.",
    "PyTorch's OpenMP threads wait passively (`OMP_WAIT_POLICY=PASSIVE`, set by the "
    "benchmark unless the environment gives another value; `omp_wait_policy` in bench.json's "
    "meta): spinning, they would take a core from XLA's threads and the torch rows would "
    'time that contention instead of the bridge (docs/torch.md, "Threads on a CPU").',
)


def select(patterns: list[str], skip: list[str] | None = None) -> tuple[list[Case], list[str]]:
    """The per-size cases and fit benchmarks to run.

    A case runs when its name contains one of `patterns` (all cases without patterns,
    except the peers benchmark, which runs only when a pattern names it) and none of
    `skip`. The floors and :data:`REFERENCES` are never skipped and run
    whenever a per-size pipeline case does: the ratios need them.

    **Raises:** `ConfigError` listing the cases when nothing is left to run.
    """
    skip = list(skip or [])

    def wanted(name: str) -> bool:
        chosen = not patterns or any(p in name for p in patterns)
        return chosen and not any(s in name for s in skip)

    pipelines = [c for c in CASES if c.kind != "floor" and wanted(c.name)]
    # The references every ratio is taken against run with any pipeline.
    always = [c for c in CASES if c.kind == "floor" or c.name in REFERENCES]
    cases = [c for c in CASES if c in pipelines or (pipelines and c in always)]
    fits = [
        name
        for name in (*FIT_CASES, *SAMPLE_CASES, *UNKNOWN_DRAW_CASES, *BATCH_CASES)
        if wanted(name)
    ]
    # The peers (other packages, installed by the bench extra) run only when named.
    fits += [name for name in PEER_CASES if patterns and wanted(name)]
    if not pipelines and not fits:
        names = ", ".join(
            [c.name for c in CASES]
            + [*FIT_CASES, *SAMPLE_CASES, *UNKNOWN_DRAW_CASES, *BATCH_CASES, *PEER_CASES]
        )
        raise ConfigError(
            f"no benchmark case matches {patterns}"
            + (f" once {skip} are skipped" if skip else "")
            + f"; cases: {names}"
        )
    return cases, fits


def release_programs() -> None:
    """Drop JAX's compiled programs (and with them their machine code).

    XLA's CPU backend maps memory for every function it compiles: a temporal frame holds
    about 1 500 maps. A whole benchmark run compiled enough programs to pass the kernel's
    limit of 65 530 maps per process (``vm.max_map_count``) and crashed in LLVM ("Cannot
    allocate memory"). Each case compiles its own programs anyway, so none are reused.
    """
    import jax

    jax.clear_caches()
    gc.collect()


def _meta() -> dict[str, Any]:
    import jax

    return {
        "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, Python "
        f"{platform.python_version()}",
        "cpu": cpu_info(),
        "jax": f"{jax.__version__} ({jax.default_backend()})",
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "retain_freed_memory": retain_freed_memory(),
        "omp_wait_policy": passive_openmp(),
        "notes": list(NOTES),
    }


#: Cases timed together with a twin, their calls alternating, since the two's difference
#: or ratio is the result: a torch layer and the same JAX call, a progressive frame and
#: the same frame from scratch.
TIMED_TOGETHER: dict[str, str] = {**PAIRS, **PROGRESSIVE_PAIRS}


def _jobs(cases: list[Case], sizes: list[int]) -> list[tuple[tuple[Case, ...], int]]:
    """What to time, size by size: each case alone, except those of
    :data:`TIMED_TOGETHER` whose twin runs too, timed with it."""
    by_name = {c.name: c for c in cases}
    pairs = TIMED_TOGETHER
    twins = {pairs[c.name] for c in cases if pairs.get(c.name) in by_name}
    jobs = []
    for n in sizes:
        for case in cases:
            if case.name in twins:
                continue
            twin = by_name.get(pairs.get(case.name, ""))
            jobs.append(((case, twin) if twin is not None else (case,), n))
    return jobs


def run_bench(
    patterns: list[str],
    out_dir: Path,
    sizes: list[int],
    repeats: int,
    *,
    skip: list[str] | None = None,
    fit_npix: int = 128,
    budget_s: float = BUDGET_S,
) -> list[dict]:
    """Run the selected cases (floors always run with them) and write the reports.

    **Arguments:**

    - `patterns`, `skip`: which cases, see :func:`select`.
    - `out_dir`: where ``bench.md`` and ``bench.json`` go (written atomically; while the
      run is going, ``bench.partial.json`` holds what is done so far).
    - `sizes`: the N of the per-size cases (even, >= 16).
    - `repeats`: timed calls per case at N <= 512, fewer at larger N, and at most
      `budget_s` seconds of them (at least 3).
    - `fit_npix`: photo size of the fit benchmark.

    **Returns:** the per-size records (the fit records are in bench.json's ``"fit"``).

    **Raises:** `ConfigError` for bad sizes or patterns; `RuntimeError` naming the cases
    that failed (after writing the reports of the others).
    """
    from invglare._core.memory import check_memory
    from invglare.files.atomic import write_json_atomic, write_text_atomic
    from invglare.files.outputs import output_folder

    if not sizes or any(n < 16 or n % 2 for n in sizes):
        raise ConfigError(f"--sizes must be even and >= 16, got {sizes}")
    if repeats < 1:
        raise ConfigError(f"--repeats must be >= 1, got {repeats}")
    if not (math.isfinite(budget_s) and budget_s > 0):
        raise ConfigError(f"--budget-s must be a finite number of seconds > 0, got {budget_s}")
    if fit_npix < 16:
        raise ConfigError(f"--fit-npix must be >= 16, got {fit_npix}")
    # A case holds a few complex N^2 buffers (field, transform, PSF) at once.
    check_memory(
        4 * 8.0 * max(sizes) ** 2, f"the benchmark at N = {max(sizes)} (--sizes {max(sizes)})"
    )
    output_folder(out_dir, "--out-dir")
    cases, fits = select(patterns, skip)
    out_dir = Path(out_dir)
    partial = out_dir / "bench.partial.json"
    meta = _meta()
    meta["load_1m_start"] = load_1m()
    started = time.perf_counter()
    records: list[dict] = []
    fit_records: list[dict] = []
    failed: list[str] = []
    meta["not_installed"] = not_installed = []

    def save_partial() -> None:
        write_json_atomic(partial, {"meta": meta, "records": records, "fit": fit_records})

    jobs = _jobs(cases, sizes)
    for job, n in tqdm(jobs, desc="bench", unit="case", disable=None):
        fns: list = []
        try:
            fns = [case.make(n) for case in job]
            missing = [case.name for case, fn in zip(job, fns, strict=True) if fn is None]
            if missing:
                log.info("skipping %s: not installed here", " + ".join(missing))
                not_installed += [name for name in missing if name not in not_installed]
                continue
            # Fewer repeats at large sizes keep the whole run to minutes.
            reps = max(3, repeats // max(1, (n // 512) ** 2))
            timings = measure_together(tuple(fns), reps, budget_s=budget_s)
        except Exception as err:  # one broken case must not lose the others' results
            names = " + ".join(c.name for c in job)
            log.error("bench case %s at N=%d failed:\n%s", names, n, traceback.format_exc())
            failed.append(f"{names} (N={n}): {type(err).__name__}: {err}")
            continue
        finally:
            fns = []
            release_programs()
        for case, timing in zip(job, timings, strict=True):
            records.append(
                {
                    "case": case.name,
                    "kind": case.kind,
                    "size": n,
                    "median_ms": round(timing.median_ms, 4),
                    "min_ms": round(timing.min_ms, 4),
                    "repeats": timing.repeats,
                    "first_call_s": round(timing.first_call_s, 4),
                    "cpu_per_wall": round(timing.cpu_per_wall, 2),
                    "load_1m": load_1m(),
                    "description": case.description,
                    "forward": case.forward,
                }
            )
        save_partial()
    _add_ratios(records)

    for name in fits:
        from invglare.bench.fit import FIT_PROBLEMS, as_json, run_fit_benchmark
        from invglare.bench.sample import run_sample_benchmark

        try:
            if name in PEER_CASES:
                from invglare.bench.peer_cases import run_peer_benchmark

                log.info("running the peers benchmark (dLux, hcipy, poppy; a minute or two)")
                record = run_peer_benchmark(repeats, budget_s)
            elif name in BATCH_CASES:
                from invglare.bench.batch import run_batch_benchmark

                log.info("running the batch benchmark %s on Dask (minutes)", name)
                record = run_batch_benchmark()
            elif name in SAMPLE_CASES:
                log.info("running the sampling benchmark %s (a few minutes)", name)
                record = run_sample_benchmark()
            elif name in UNKNOWN_DRAW_CASES:
                from invglare.bench.unknown_draw import run_unknown_draw_benchmark

                log.info("running %s: a fit of an eye the model did not draw (minutes)", name)
                record = run_unknown_draw_benchmark()
            else:
                log.info("running the fit benchmark %s at %d px (minutes)", name, fit_npix)
                record = run_fit_benchmark(FIT_PROBLEMS[name], fit_npix)
            fit_records.append(as_json(record))
        except Exception as err:
            log.error("benchmark %s failed:\n%s", name, traceback.format_exc())
            failed.append(f"{name}: {type(err).__name__}: {err}")
        finally:
            release_programs()
        save_partial()

    meta["load_1m_end"] = load_1m()
    meta["wall_s"] = round(time.perf_counter() - started, 1)
    meta["failed"] = failed
    records, fit_records, meta = _keep_previous(out_dir / "bench.json", records, fit_records, meta)
    write_json_atomic(
        out_dir / "bench.json", {"meta": meta, "records": records, "fit": fit_records}
    )
    write_text_atomic(out_dir / "bench.md", render_markdown(records, meta, fit_records))
    partial.unlink(missing_ok=True)
    log.info("wrote %s and %s", out_dir / "bench.md", out_dir / "bench.json")
    if failed:
        raise RuntimeError("benchmark cases failed: " + "; ".join(failed))
    return records


def _keep_previous(
    path: Path, records: list[dict], fit_records: list[dict], meta: dict
) -> tuple[list[dict], list[dict], dict]:
    """Carry over the sections of an existing bench.json that this run did not measure.

    The per-size timings are one section (their ratios need one run), kept whole when no
    per-size case ran; fit records are kept per fit case (each is self-contained and
    carries its own date and load). So ``invglare bench fit`` refreshes the fit section
    and leaves the timings, and ``invglare bench --skip fit`` the other way round.
    """
    import json

    if not path.is_file():
        return records, fit_records, meta
    try:
        old = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        log.warning("not keeping anything of %s: %s", path, err)
        return records, fit_records, meta
    if not isinstance(old, dict) or not isinstance(old.get("records"), list):
        return records, fit_records, meta  # an older format: nothing to carry over
    if not records and old["records"]:
        records = old["records"]
        meta = {**meta, "timings_from": old.get("meta", {})}
        log.info("kept the per-size timings of %s (measured %s)", path, old["meta"].get("date"))
    ran = {r["case"] for r in fit_records}
    kept = [r for r in old.get("fit", []) if isinstance(r, dict) and r.get("case") not in ran]
    return records, kept + fit_records, meta


def _add_ratios(records: list[dict]) -> None:
    """Ratios from the records themselves (in place).

    - ``ratio``: median over the fastest floor (kind ``"floor"``) at the same size;
    - ``vs_jax_fft``: median over ``fft_jax`` at the same size (JAX's own FFT);
    - ``vs_forward``: a gradient's median over its forward case's at the same size.

    Each is None where its reference was not measured.
    """
    floors: dict[int, float] = {}
    for r in records:
        if r["kind"] == "floor":
            floors[r["size"]] = min(floors.get(r["size"], float("inf")), r["median_ms"])
    by_key = {(r["case"], r["size"]): r for r in records}
    for r in records:
        floor = floors.get(r["size"])
        r["floor_ms"] = floor
        r["ratio"] = round(r["median_ms"] / floor, 3) if floor else None
        jfft = by_key.get(("fft_jax", r["size"]))
        r["vs_jax_fft"] = round(r["median_ms"] / jfft["median_ms"], 3) if jfft else None
        fwd = by_key.get((r["forward"], r["size"])) if r.get("forward") else None
        r["vs_forward"] = round(r["median_ms"] / fwd["median_ms"], 3) if fwd else None


def _missing_floors(meta: dict) -> str:
    """A sentence naming the FFT floors the timed run could not measure (none: empty)."""
    timed = meta.get("timings_from") or meta
    missing = [n for n in timed.get("not_installed", []) if n.startswith("fft_floor_")]
    if not missing:
        return ""
    return (
        f" Not installed for this run: {', '.join(f'`{n}`' for n in missing)} (the `bench` "
        "extra installs pyfftw), so the floor is the other library's alone and the ratios "
        "compare with it."
    )


def cpu_line(cpu: dict | None) -> str:
    """The processor and its vector extensions: runs on other machines differ by them."""
    if not cpu:
        return "CPU: not recorded."
    flags = ", ".join(cpu.get("vector_extensions", [])) or "none read"
    return f"CPU: {cpu.get('model')}; vector extensions {flags}."


def _num(x: float | None, fmt: str) -> str:
    return "" if x is None else format(x, fmt)


def render_markdown(records: list[dict], meta: dict, fit_records: list[dict] | None = None) -> str:
    """bench.md: notes, a ratio overview (case x N), the full table, the fit section."""
    from invglare.bench.batch import batch_markdown
    from invglare.bench.fit import fit_markdown
    from invglare.bench.peer_cases import peers_markdown
    from invglare.bench.sample import sample_markdown
    from invglare.bench.unknown_draw import unknown_draw_markdown

    lines = [
        "# invglare benchmarks",
        "",
        f"Measured {meta['date']} on {meta['machine']}; JAX {meta['jax']}. Load average "
        f"(1 min) {meta.get('load_1m_start')} at the start, {meta.get('load_1m_end')} at the "
        f"end; the run took {meta.get('wall_s', '?')} s.",
        "",
        cpu_line(meta.get("cpu")),
        "",
        *[f"- {note}" for note in meta.get("notes", [])],
        "",
    ]
    earlier = meta.get("timings_from")
    if earlier:
        lines += [
            f"The per-size timings below are from an earlier run ({earlier.get('date')}, load "
            f"{earlier.get('load_1m_start')} to {earlier.get('load_1m_end')}, "
            f"{earlier.get('wall_s', '?')} s); this run only refreshed the fit section.",
            "",
        ]
    if records:
        sizes = sorted({r["size"] for r in records})
        names = list(dict.fromkeys(r["case"] for r in records))
        by_key = {(r["case"], r["size"]): r for r in records}
        lines += [
            "## Ratio to the FFT floor",
            "",
            "Median time over the fastest bare complex64 FFT of the same size (scipy or "
            "pyfftw, 2 threads) measured in this run." + _missing_floors(meta),
            "",
            "| case | " + " | ".join(f"N={n}" for n in sizes) + " |",
            "|---|" + "---:|" * len(sizes),
        ]
        for name in names:
            cells = []
            for n in sizes:
                r = by_key.get((name, n))
                cells.append(_num(r["ratio"], ".2f") if r else "")
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
        lines += [
            "",
            "## All timings",
            "",
            "`vs jax fft`: over JAX's bare FFT of the same size; `vs forward`: a gradient "
            "over its forward pass. Medians of repeated calls after compilation.",
            "",
            "| case | N | median ms | floor ms | ratio | vs jax fft | vs forward "
            "| first call s | repeats | cpu/wall | load |",
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for r in records:
            lines.append(
                f"| {r['case']} | {r['size']} | {r['median_ms']:.3f} "
                f"| {_num(r['floor_ms'], '.3f')} | {_num(r['ratio'], '.2f')} "
                f"| {_num(r.get('vs_jax_fft'), '.2f')} | {_num(r['vs_forward'], '.2f')} "
                f"| {_num(r.get('first_call_s'), '.2f')} | {r.get('repeats', '')} "
                f"| {_num(r.get('cpu_per_wall'), '.2f')} | {_num(r.get('load_1m'), '.1f')} |"
            )
        for section in (stage_markdown, paper_markdown, overhead_markdown, quad_markdown):
            extra = section(records)
            lines += ["", *extra] if extra else []
        lines += ["", "Cases:", ""]
        descriptions = {r["case"]: r.get("description", "") for r in records}
        lines += [f"- `{name}`: {descriptions[name]}" for name in names]
    failures = list(meta.get("failed", [])) + list((earlier or {}).get("failed", []))
    if failures:
        lines += ["", "## Failed cases", ""]
        lines += [f"- {failure}" for failure in failures]
    for record in fit_records or []:
        kind = record.get("kind")
        markdown = {
            "sample": sample_markdown,
            "peers": peers_markdown,
            "unknown_draw": unknown_draw_markdown,
            "batch": batch_markdown,
        }.get(kind, fit_markdown)
        section = markdown(record)
        lines += ["", *section]
    return "\n".join(lines) + "\n"
