"""The holographic eye's benchmark cases: well formed, the paper's numbers, they run.

No timing is asserted: speed is what `invglare bench` reports.
"""

from __future__ import annotations

import pytest

from invglare.bench.holographic_cases import (
    HOLOGRAPHIC_CASES,
    PAPER_S,
    bench_model,
    nearest_depth_mm,
    paper_markdown,
)


def test_cases_are_named_once_and_quote_the_paper():
    names = [c.name for c in HOLOGRAPHIC_CASES]
    assert len(names) == len(set(names)) == 10
    assert all(c.kind == "pipeline" for c in HOLOGRAPHIC_CASES)
    lashes_tear = next(c for c in HOLOGRAPHIC_CASES if c.name == "holo_lashes_tear")
    assert "191 s" in lashes_tear.description and "5645 s" in lashes_tear.description
    # The paper's Tables 3.1 and 3.3, as printed.
    assert PAPER_S[("3.1", 512, 64)] == {"base": 975, "lashes": 1269, "lashes_tear": 1563}
    assert PAPER_S[("3.3", 256, 16)] == {"base": 153, "lashes": 171, "lashes_tear": 191}


def test_nearest_depth_formula_is_the_models():
    for n in (32, 256):
        model = bench_model(n, "lashes_tear", False)
        assert model.nearest_depth_mm() == pytest.approx(nearest_depth_mm(n), rel=1e-12)


# That the cases run (holo_base, holo_depth_base, holo_fft_floor and the rest, at N = 32,
# finite and not all zero) is checked once, by tests/bench/test_bench.py's
# test_every_case_builds_and_runs_at_a_tiny_size_with_finite_output (a test here built and
# compiled three of them again).


def test_paper_markdown_puts_the_paper_beside_the_measurement():
    records = [
        {"case": "holo_lashes_tear", "size": 512, "median_ms": 5000.0},
        {"case": "holo_fft_floor", "size": 512, "median_ms": 2500.0},
        {"case": "holo_depth_base", "size": 256, "median_ms": 100.0},
    ]
    lines = paper_markdown(records)
    assert lines[0].startswith("## Holographic eye")
    row = next(line for line in lines if "holo_lashes_tear" in line)
    assert "| 5645 | 5.00 | 1129x | 2.00 |" in row
    assert any("| 3.1 | holo_depth_base | 256 | 16 | 39 | 0.10 | 390x |" in line for line in lines)
    assert paper_markdown([]) == []
