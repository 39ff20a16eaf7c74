"""The quad report's fit of a heptagon by the polygon method and by the MFT
(:func:`invglare.bench.quad_report.fit_comparison`): it runs, and both recover the truth
within their own errors (the photo is made by the closed form, not by either method)."""

from __future__ import annotations

import pytest

from invglare.bench.quad_report import fit_comparison


@pytest.mark.slow
def test_both_methods_recover_the_heptagon_within_their_errors() -> None:
    fits = fit_comparison()
    assert set(fits) == {"mft", "polygon"}
    for method, f in fits.items():
        assert abs(f["rotation_error_deg"]) < 3 * f["rotation_se_deg"], (method, f)
        assert abs(f["diameter_error_mm"]) < 3 * f["diameter_se_mm"], (method, f)
        assert 0.8 < f["chi2_per_pixel"] < 1.3, (method, f)
        assert 0 < f["steps"] < 100 and f["solve_s"] > 0, (method, f)
