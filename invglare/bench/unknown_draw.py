"""The benchmark of a fit of an eye the model did not draw: `fit_unknown_draw`.

A real eye has no seed. The case fits ``fits/eye_daylight_other_draws.toml`` (statistics
weighed by the scatter between simulated eyes) to the first of its bundled photos, a
128² daylight eye drawn with eye seed 2000 (the model config's is 7) and truths away from
the config's values, as ``invglare fit`` would. It records the wall time of the whole fit
(compilation included), the fitted values with their standard errors against the truth,
and the load.
"""

from __future__ import annotations

import datetime as dt
import time
from pathlib import Path
from typing import Any

from invglare.bench.timing import load_1m

#: The case's name (run once, like the fit benchmarks).
UNKNOWN_DRAW_CASES = ("fit_unknown_draw",)

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "fits" / "eye_daylight_other_draws.toml"


def run_unknown_draw_benchmark() -> dict[str, Any]:
    """Fit the photo of an eye the model did not draw; return one JSON-ready record."""
    import jax

    from invglare.config.fit import load_fit

    record: dict[str, Any] = {
        "case": "fit_unknown_draw",
        "kind": "unknown_draw",
        "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "load_1m_start": load_1m(),
        "config": str(CONFIG.relative_to(ROOT)),
    }
    with jax.enable_x64(True):
        t0 = time.perf_counter()
        setup = load_fit(CONFIG)
        result = setup.fit()
        record["wall_s"] = time.perf_counter() - t0
    record["photo"] = str(setup.target_path.relative_to(ROOT))
    record["npix"] = int(setup.target.shape[0])
    record["timing_s"] = dict(result.timing_s)
    record["converged"] = bool(result.converged)
    record["message"] = result.message
    record["parameters"] = {
        p: {
            "value": result.values[p],
            "stderr": result.stderr[p],
            "truth": (result.truth or {}).get(p),
        }
        for p in result.paths
    }
    record["load_1m_end"] = load_1m()
    return record


def unknown_draw_markdown(record: dict[str, Any]) -> list[str]:
    """The case's section of bench.md."""
    lines = [
        f"## Fit of an eye the model did not draw: {record['case']} ({record['npix']}² photo)",
        "",
        f"Measured {record['date']}: `{record['config']}` on `{record['photo']}`, a "
        f"{record['npix']}² daylight eye drawn with another seed than the model's. "
        f"Wall time {record['wall_s']:.0f} s for the whole fit, compilation included "
        f"(compile {record['timing_s'].get('compile', 0):.0f} s, solve "
        f"{record['timing_s'].get('solve', 0):.0f} s). Load (1 min) {record['load_1m_start']} "
        f"at the start, {record['load_1m_end']} at the end. {record['message']}.",
        "",
        "| parameter | value | stderr | truth | (value - truth) / stderr |",
        "|---|---:|---:|---:|---:|",
    ]
    for path, p in record["parameters"].items():
        truth = p["truth"]
        pull = (
            "—"
            if truth is None or not p["stderr"]
            else f"{(p['value'] - truth) / p['stderr']:+.2f}"
        )
        lines.append(
            f"| `{path}` | {p['value']:.5g} | {p['stderr']:.3g} | "
            f"{'—' if truth is None else format(truth, '.5g')} | {pull} |"
        )
    return lines


__all__ = ["UNKNOWN_DRAW_CASES", "run_unknown_draw_benchmark", "unknown_draw_markdown"]
