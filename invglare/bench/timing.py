"""Wall-clock timing of jitted callables: warm up (compile), then the median of repeats."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable

import jax


def _block(result):
    return jax.tree_util.tree_map(
        lambda x: x.block_until_ready() if hasattr(x, "block_until_ready") else x, result
    )


def time_ms(fn: Callable[[], object], repeats: int, warmup: int = 2) -> tuple[float, float]:
    """Median and minimum wall time of ``fn()`` in ms, after `warmup` untimed calls.

    JAX results are waited for (``block_until_ready``), so asynchronous dispatch
    does not hide the work.
    """
    for _ in range(warmup):
        _block(fn())
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        _block(fn())
        times.append((time.perf_counter() - start) * 1e3)
    return statistics.median(times), min(times)
