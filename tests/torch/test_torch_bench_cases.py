"""The torch bench cases run, their twins compute the same values, the table reads records."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from invglare.bench.torch_cases import PAIRS, TORCH_CASES, overhead_markdown, overhead_rows

TINY = 32
MAKERS = {c.name: c.make for c in TORCH_CASES}


def _numpy(result):
    if isinstance(result, torch.Tensor):
        return [result.detach().numpy()]
    if isinstance(result, tuple | list):
        return [a for r in result for a in _numpy(r)]
    return [np.asarray(result)]


@pytest.mark.parametrize("case", list(PAIRS))
def test_torch_case_and_its_twin_agree(case):
    a, b = MAKERS[case](TINY)(), MAKERS[PAIRS[case]](TINY)()
    got, want = _numpy(a), _numpy(b)
    if case.endswith("_jax") or not case.endswith("grad"):
        got, want = got[:1], want[:1]  # the forward twins also return the finite flags
    assert len(got) == len(want)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(g.reshape(w.shape), w, rtol=1e-5, atol=1e-8)


def test_overhead_rows_from_records():
    records = [
        {"case": "torch_psf", "size": 256, "median_ms": 1.25, "min_ms": 1.0},
        {"case": "torch_psf_jax", "size": 256, "median_ms": 1.0, "min_ms": 0.95},
        {"case": "torch_glare", "size": 256, "median_ms": 5.0, "min_ms": 5.0},  # no twin
    ]
    (row,) = overhead_rows(records)
    assert row["ratio"] == 1.25 and row["excess_ms"] == 0.25 and row["goal_met"]
    assert not overhead_rows(records[:1])
    (low,) = overhead_rows(records, "min_ms")
    assert low["goal_met"] and low["ratio"] == pytest.approx(1.0 / 0.95, rel=1e-3)
    assert any("| torch_psf | 256 |" in line for line in overhead_markdown(records))
