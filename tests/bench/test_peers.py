"""``invglare bench peers``: the closed-form references, the accuracy measure, invglare's own
setup against them, the side-by-side timing, the "not installed" rows and the wiring into
``invglare bench`` (selection, bench.md's CPU line and peers section)."""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest

from invglare.bench import peer_cases, runner
from invglare.bench.peer_cases import (
    NPIX,
    PeerSetup,
    cpu_info,
    measure_side_by_side,
    output_coords_rad,
    peers_markdown,
    pixel_scale_rad,
    psf_error,
    reference_psf,
    run_peer_benchmark,
)


def test_sampling_is_four_pixels_per_lambda_over_d():
    lam_over_d = 550e-6 / 4.0
    assert pixel_scale_rad() * 4 == pytest.approx(lam_over_d, rel=1e-12)
    pixel, corner = output_coords_rad("pixel"), output_coords_rad("corner")
    assert pixel[NPIX // 2] == 0.0
    assert corner[NPIX // 2 - 1] == -corner[NPIX // 2]  # the axis between two pixels


@pytest.mark.parametrize("shape", ["airy", "hexagon"])
def test_references_are_unit_energy_pixels_with_the_right_peak(shape):
    ref = reference_psf(shape, "pixel")
    # Peak A / lambda^2 times the pixel solid angle (Parseval); A of the disk or hexagon.
    area = math.pi * 4.0**2 / 4 if shape == "airy" else 3 * math.sqrt(3) / 2 * 2.0**2
    peak = area / (550e-6) ** 2 * pixel_scale_rad() ** 2
    assert ref[NPIX // 2, NPIX // 2] == pytest.approx(peak, rel=1e-12)
    # +-64 lambda/D holds all but ~0.3 % (Airy: 1 - 2 / (pi^2 * 64) for the encircled part).
    assert 0.995 < ref.sum() < 1.0
    corner = reference_psf(shape, "corner")
    c = NPIX // 2
    np.testing.assert_allclose(corner[c - 1, c - 1], corner[c, c], rtol=1e-10)


def test_psf_error_scales_to_the_reference_energy_first():
    ref = reference_psf("airy", "pixel")
    assert psf_error(3.0 * ref, ref)["max_err"] == pytest.approx(0.0, abs=1e-14)
    bumped = ref.copy()
    bumped[0, 0] += 1e-3 * ref.max()
    err = psf_error(bumped, ref)
    assert err["max_err"] == pytest.approx(1e-3, rel=1e-2)
    assert err["rms_err"] < err["max_err"]


@pytest.mark.parametrize("shape", ["airy", "hexagon"])
def test_invglare_matches_the_closed_forms(shape):
    setup = peer_cases._invglare(shape)
    psf = np.asarray(setup.forward())
    assert psf.shape == (NPIX, NPIX)
    err = psf_error(psf, reference_psf(shape, setup.centring))
    # Measured 1.2e-3 (Airy) and 1.4e-3 (hexagon) of the peak; rms 1e-5.
    assert err["max_err"] < 2e-3
    assert err["rms_err"] < 2e-5
    grad = float(setup.gradient())
    assert math.isfinite(grad) and grad != 0.0


def test_missing_peers_are_none(monkeypatch):
    for module in ("dLux", "hcipy", "poppy"):
        monkeypatch.setitem(sys.modules, module, None)  # import raises ImportError
    assert peer_cases._dlux("airy") is None
    assert peer_cases._hcipy("hexagon") is None
    assert peer_cases._poppy("airy") is None


def test_side_by_side_times_every_function_in_rounds():
    calls = []
    fns = {"a": lambda: calls.append("a"), "b": lambda: calls.append("b")}
    timings = measure_side_by_side(fns, rounds=4)
    assert set(timings) == {"a", "b"}
    assert timings["a"]["repeats"] == 4
    # Two untimed calls each (compile, warm-up), then interleaved rounds a b a b ...
    assert calls == ["a", "a", "b", "b"] + ["a", "b"] * 4


def test_run_reports_not_installed_and_failed_peers(monkeypatch):
    ref = {s: {c: reference_psf(s, c) for c in ("pixel", "corner")} for s in ("airy", "hexagon")}

    def fake_invglare(shape):
        psf = ref[shape]["pixel"]
        return PeerSetup(lambda: psf, lambda: 0.0, "pixel", "0", "fake")

    def fake_slow(shape):
        psf = 2.0 * ref[shape]["corner"]  # another normalisation, another grid

        def slow():
            np.fft.fft2(np.ones((NPIX, NPIX)))
            return psf

        return PeerSetup(slow, None, "corner", "1", "fake, no gradient")

    def broken(shape):
        raise RuntimeError("no such aperture")

    monkeypatch.setitem(peer_cases.SETUPS, "invglare", fake_invglare)
    monkeypatch.setitem(peer_cases.SETUPS, "dlux", lambda shape: None)
    monkeypatch.setitem(peer_cases.SETUPS, "hcipy", fake_slow)
    monkeypatch.setitem(peer_cases.SETUPS, "poppy", broken)
    record = run_peer_benchmark(repeats=3, budget_s=5.0)
    rows = {(r["shape"], r["code"]): r for r in record["rows"]}
    assert rows["airy", "dlux"]["status"] == "not installed"
    assert rows["hexagon", "poppy"]["status"].startswith("failed: RuntimeError")
    slow = rows["airy", "hcipy"]
    assert slow["max_err"] == pytest.approx(0.0, abs=1e-12)
    assert slow["gradient"] is None
    assert slow["forward"]["ratio"] > 0 and slow["forward"]["speedup"] > 0
    assert slow["forward"]["speedup_min"] > 0 and "by minima" in "\n".join(peers_markdown(record))
    assert set(record["floors"]["airy"]) >= {"fft_floor_scipy", "fft_jax"}
    assert record["cpu"]["model"]
    text = "\n".join(peers_markdown(record))
    assert "| airy | dlux | not installed |" in text
    assert "x faster" in text and "n/a" in text


def test_cpu_info_reads_model_and_vector_flags():
    info = cpu_info()
    assert isinstance(info["model"], str) and info["model"]
    assert set(info["vector_extensions"]) <= set(peer_cases.VECTOR_FLAGS)
    try:
        text = open("/proc/cpuinfo").read()
    except OSError:
        return
    flags = next(
        (ln.split(":", 1)[1].split() for ln in text.splitlines() if ln.startswith("flags")), []
    )
    assert info["vector_extensions"] == [f for f in peer_cases.VECTOR_FLAGS if f in flags]


def test_bench_selects_peers_and_writes_its_section():
    cases, fits = runner.select(["peers"])
    assert cases == [] and fits == ["peers"]
    assert "peers" not in runner.select([])[1]  # not part of a plain `invglare bench`
    record = {
        "kind": "peers",
        "case": "peers",
        "cpu": {"model": "Test CPU", "vector_extensions": ["avx2"], "logical_cpus": 2},
        "rows": [{"code": "poppy", "shape": "airy", "status": "not installed"}],
        "floors": {},
    }
    meta = {"date": "today", "machine": "m", "jax": "j", "cpu": record["cpu"], "notes": []}
    text = runner.render_markdown([], meta, [record])
    assert "CPU: Test CPU; vector extensions avx2." in text
    assert "## Peers: the same PSF in dLux, hcipy and poppy" in text
    assert "| airy | poppy | not installed |" in text
