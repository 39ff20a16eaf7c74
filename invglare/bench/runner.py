"""``invglare bench``: time every case at every size and write reports/bench.{md,json}."""

from __future__ import annotations

import datetime as dt
import logging
import os
import platform
from pathlib import Path

from tqdm import tqdm

from invglare.bench.cases import CASES, Case
from invglare.bench.timing import time_ms
from invglare.errors import ConfigError

log = logging.getLogger("invglare")


def _select(patterns: list[str]) -> list[Case]:
    if not patterns:
        return list(CASES)
    chosen = [c for c in CASES if c.kind == "floor" or any(p in c.name for p in patterns)]
    if all(c.kind == "floor" for c in chosen):
        names = ", ".join(c.name for c in CASES)
        raise ConfigError(f"no benchmark case matches {patterns}; cases: {names}")
    return chosen


def run_bench(patterns: list[str], out_dir: Path, sizes: list[int], repeats: int) -> list[dict]:
    """Run the selected cases (floors always run: every ratio needs them) and write reports."""
    import jax

    from invglare.io.atomic import write_json_atomic, write_text_atomic

    if any(n < 16 or n % 2 for n in sizes):
        raise ConfigError(f"bench sizes must be even and >= 16, got {sizes}")
    cases = _select(patterns)
    records: list[dict] = []
    jobs = [(case, n) for n in sizes for case in cases]
    for case, n in tqdm(jobs, desc="bench", unit="case", disable=None):
        fn = case.make(n)
        if fn is None:
            log.info("skipping %s: not installed here", case.name)
            continue
        # Fewer repeats at large sizes keep the whole run to a few minutes.
        reps = max(3, repeats // max(1, (n // 512) ** 2))
        median, best = time_ms(fn, reps)
        records.append(
            {
                "case": case.name,
                "kind": case.kind,
                "size": n,
                "median_ms": round(median, 4),
                "min_ms": round(best, 4),
                "repeats": reps,
                "description": case.description,
                "forward": case.forward,
            }
        )
    _add_ratios(records)
    meta = {
        "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, {platform.python_version()}",
        "jax": f"{jax.__version__} ({jax.default_backend()})",
    }
    out_dir = Path(out_dir)
    write_json_atomic(out_dir / "bench.json", records)
    write_text_atomic(out_dir / "bench.md", render_markdown(records, meta))
    log.info("wrote %s and %s", out_dir / "bench.md", out_dir / "bench.json")
    return records


def _add_ratios(records: list[dict]) -> None:
    """ratio = median / fastest floor at the same size; gradients also get vs_forward."""
    floors: dict[int, float] = {}
    for r in records:
        if r["kind"] == "floor":
            floors[r["size"]] = min(floors.get(r["size"], float("inf")), r["median_ms"])
    by_key = {(r["case"], r["size"]): r for r in records}
    for r in records:
        floor = floors.get(r["size"])
        r["floor_ms"] = floor
        r["ratio"] = round(r["median_ms"] / floor, 3) if floor else None
        fwd = by_key.get((r["forward"], r["size"])) if r["forward"] else None
        r["vs_forward"] = round(r["median_ms"] / fwd["median_ms"], 3) if fwd else None


def render_markdown(records: list[dict], meta: dict) -> str:
    lines = [
        "# invglare benchmarks",
        "",
        f"Measured {meta['date']} on {meta['machine']}; JAX {meta['jax']}.",
        "",
        "`ratio` is the case's median time over the fastest bare complex64 FFT of the same",
        "size measured in this run (`floor_ms`); `vs_forward` is a gradient's time over its",
        "forward pass. Times are medians of repeated calls after compilation.",
        "",
        "| case | N | median ms | floor ms | ratio | vs forward | what |",
        "|---|---:|---:|---:|---:|---:|---|",
    ]
    for r in records:
        vs = f"{r['vs_forward']:.2f}" if r["vs_forward"] else ""
        ratio = f"{r['ratio']:.2f}" if r["ratio"] else ""
        floor = f"{r['floor_ms']:.3f}" if r["floor_ms"] else ""
        lines.append(
            f"| {r['case']} | {r['size']} | {r['median_ms']:.3f} | {floor} | {ratio} | {vs} "
            f"| {r['description']} |"
        )
    return "\n".join(lines) + "\n"
