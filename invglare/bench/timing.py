"""Wall-clock timing of jitted callables: the first call (compile), then the median of repeats."""

from __future__ import annotations

import dataclasses
import os
import statistics
import time
from collections.abc import Callable

import jax


def _block(result):
    return jax.tree_util.tree_map(
        lambda x: x.block_until_ready() if hasattr(x, "block_until_ready") else x, result
    )


def load_1m() -> float | None:
    """The 1-minute load average (None where the OS has none): how busy the machine was."""
    try:
        return round(os.getloadavg()[0], 2)
    except (AttributeError, OSError):
        return None


@dataclasses.dataclass(frozen=True)
class Timing:
    """What :func:`measure` found.

    - `median_ms`, `min_ms`: over the timed repeats, after compilation.
    - `first_call_s`: the first call, i.e. tracing + compilation + one run.
    - `repeats`: how many calls were timed (fewer than asked when the budget ran out).
    - `cpu_per_wall`: process CPU time over wall time during the timed repeats; about 1
      for single-threaded work on an idle machine, up to the thread count for
      multi-threaded work, and below 1 when other processes take the cores.
    """

    median_ms: float
    min_ms: float
    first_call_s: float
    repeats: int
    cpu_per_wall: float


def measure(
    fn: Callable[[], object], repeats: int, budget_s: float | None = None, min_repeats: int = 3
) -> Timing:
    """Time ``fn()``: a first call (compilation, reported apart), a warm-up, then the repeats.

    JAX results are waited for (``block_until_ready``), so asynchronous dispatch does
    not hide the work. A second warm-up call runs only when the first was quick (< 1 s):
    it settles caches (FFT plans, allocator) and costs nothing noticeable, whereas for
    a case taking seconds per call it would double the run for no information.

    **Arguments:**

    - `repeats`: calls to time at most.
    - `budget_s`: stop timing once this many seconds of repeats are spent (after at
      least `min_repeats` calls); None for no limit.
    """
    return measure_together((fn,), repeats, budget_s, min_repeats)[0]


def measure_together(
    fns: tuple[Callable[[], object], ...],
    repeats: int,
    budget_s: float | None = None,
    min_repeats: int = 3,
) -> list[Timing]:
    """:func:`measure` of callables whose times are compared, their calls alternating.

    Each repeat calls every function once in turn, so a drift of the machine's load
    falls on all of them alike (a torch layer and its JAX twin: their difference is
    the measurement). `budget_s` counts the repeats of all of them; `cpu_per_wall` is
    the whole loop's.
    """
    firsts = []
    for fn in fns:
        start = time.perf_counter()
        _block(fn())
        firsts.append(time.perf_counter() - start)
        if firsts[-1] < 1.0:
            _block(fn())
    times: list[list[float]] = [[] for _ in fns]
    cpu0, wall0 = time.process_time(), time.perf_counter()
    for i in range(max(repeats, 1)):
        spent = sum(sum(t) for t in times) / 1e3
        if budget_s is not None and i >= min_repeats and spent > budget_s:
            break
        for fn, own in zip(fns, times, strict=True):
            t0 = time.perf_counter()
            _block(fn())
            own.append((time.perf_counter() - t0) * 1e3)
    wall = time.perf_counter() - wall0
    cpu = time.process_time() - cpu0
    return [
        Timing(
            median_ms=statistics.median(own),
            min_ms=min(own),
            first_call_s=first,
            repeats=len(own),
            cpu_per_wall=cpu / wall if wall > 0 else float("nan"),
        )
        for own, first in zip(times, firsts, strict=True)
    ]
