"""The benchmark command's plumbing: every case runs, ratios come from the records, reports.

No timing is asserted anywhere: speed is what `invglare bench` reports, not a test outcome.
The eye and Kakimoto cases and the fit benchmark compile large XLA programs (minutes on a
busy 2-core machine), so they are marked slow.
"""

import importlib.util
import json
import math
import os
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest
from typer.testing import CliRunner

from invglare.bench import runner, torch_cases
from invglare.bench.batch import BATCH_CASES
from invglare.bench.fit import FIT_CASES, FitProblem, FreeParameter, fit_markdown, run_fit_benchmark
from invglare.bench.runner import (
    CASES,
    _add_ratios,
    _keep_previous,
    render_markdown,
    run_bench,
    select,
)
from invglare.bench.sample import SAMPLE_CASES
from invglare.bench.temporal_cases import STAGES, stage_markdown
from invglare.bench.timing import measure, measure_together
from invglare.bench.unknown_draw import UNKNOWN_DRAW_CASES
from invglare.cli import app
from invglare.errors import ConfigError

TINY = 32
#: Cases whose compilation takes minutes on a loaded 2-core machine.
HEAVY = ("eye_", "kakimoto_", "holo_", "torch_")


def _float_leaves(tree) -> list[np.ndarray]:
    return [
        np.asarray(x)
        for x in jax.tree_util.tree_leaves(tree)
        if hasattr(x, "dtype") and np.issubdtype(np.asarray(x).dtype, np.inexact)
    ]


#: Gradient cases of the heavy models are left to their own suites (test_eye, test_kakimoto
#: check those gradients against finite differences); here the gradient plumbing is
#: exercised by the light cases (psf_mono_grad, convolve_rgb_grad), at a fraction of the
#: compile time.
HEAVY_GRADS = ("eye_raster_grad", "kakimoto_eye_psf_grad")
#: Per-size cases whose cost does not depend on N (the coefficients of 1000 ghosts at 256
#: harmonics: ~10 s at any N); their code path runs in the smaller veiling cases.
SIZE_FREE = ("veiling_K1000_H256",)


#: Case-name prefixes whose cases need a library that invglare's test install may lack.
OPTIONAL_LIBRARIES = (("fft_floor_pyfftw", "pyfftw"), ("torch_", "torch"))


@pytest.mark.parametrize(
    "case",
    [
        pytest.param(c, id=c.name, marks=[pytest.mark.slow] if c.name.startswith(HEAVY) else [])
        for c in CASES
        # The temporal stages run, chained, in the test that compares them with the frame,
        # which also builds and checks temporal_frame itself (one build, not two).
        if c.name not in HEAVY_GRADS + SIZE_FREE + ("temporal_frame",)
        and not c.name.startswith("temporal_stage_")
    ],
)
@pytest.mark.slow
def test_every_case_builds_and_runs_at_a_tiny_size_with_finite_output(case):
    fn = case.make(TINY)
    if fn is None:
        # Unavailable is right only for a case of an optional library, where it is missing.
        library = next(
            (lib for prefix, lib in OPTIONAL_LIBRARIES if case.name.startswith(prefix)), None
        )
        assert library is not None, f"{case.name} is unavailable, but needs no optional library"
        assert importlib.util.find_spec(library) is None, f"{case.name}: {library} is installed"
        return
    _check_tiny_output(case, fn())


def _check_tiny_output(case, output) -> None:
    """What every case's output at TINY must be: finite float arrays, not all zero."""
    leaves = _float_leaves(output)
    assert leaves, f"{case.name} returned no float arrays"
    for leaf in leaves:
        assert np.all(np.isfinite(leaf)), case.name
    if case.forward is not None:
        # A gradient case: the scalar it differentiates depends on its inputs.
        assert any(np.any(leaf != 0) for leaf in leaves), case.name
    else:
        # A forward case: a non-trivial image (an FFT, raster or PSF).
        assert max(leaf.size for leaf in leaves) >= (TINY // 2) ** 2
        assert any(np.any(leaf != 0) for leaf in leaves), case.name


def test_case_names_are_unique_and_gradients_name_an_existing_forward():
    names = [c.name for c in CASES]
    assert len(names) == len(set(names))
    assert not set(names) & set(FIT_CASES)
    for c in CASES:
        assert c.kind in ("floor", "pipeline")
        if c.forward is not None:
            assert c.forward in names


# --------------------------------------------------------------------------------------
# ratios, selection, reports


def _rec(case, size, ms, kind="pipeline", forward=None):
    return {"case": case, "kind": kind, "size": size, "median_ms": ms, "forward": forward}


@pytest.mark.slow
def test_temporal_stages_chain_to_the_frame_and_are_tabulated_with_their_shares():
    """The stage cases are the frame's pieces: chained, they give its display values."""
    by_name = {c.name: c for c in CASES}
    output = by_name["temporal_frame"].make(TINY)()
    # temporal_frame's own check of test_every_case_builds_and_runs_at_a_tiny_size_... (it
    # is left out there: its build and compile are the costly part, and are shared here).
    _check_tiny_output(by_name["temporal_frame"], output)
    _, frame = output
    staged = by_name["temporal_stage_tonemap"].make(TINY)()
    assert staged.shape == frame.shape == (TINY, TINY, 3)
    np.testing.assert_allclose(np.asarray(staged), np.asarray(frame), atol=1e-5)

    times = dict(zip([name for name, _ in STAGES], [1.0, 2.0, 3.0, 4.0, 10.0], strict=True))
    records = [_rec(f"temporal_stage_{name}", 64, ms) for name, ms in times.items()]
    md = "\n".join(stage_markdown([*records, _rec("temporal_frame", 64, 19.0)]))
    row = "| 64 | 1.0 (5 %) | 2.0 (10 %) | 3.0 (15 %) | 4.0 (20 %) | 10.0 (50 %) | 20.0 | 19.0 |"
    assert row in md
    assert stage_markdown([_rec("temporal_frame", 64, 19.0)]) == []


def test_add_ratios_from_synthetic_records():
    records = [
        _rec("fft_floor_scipy", 64, 2.0, "floor"),
        _rec("fft_floor_pyfftw", 64, 1.0, "floor"),
        _rec("fft_jax", 64, 4.0),
        _rec("psf_mono", 64, 10.0),
        _rec("psf_mono_grad", 64, 25.0, forward="psf_mono"),
        _rec("fft_floor_scipy", 128, 8.0, "floor"),
        _rec("psf_mono_grad", 128, 30.0, forward="psf_mono"),  # its forward is missing
        _rec("psf_mono", 256, 5.0),  # no floor measured at this size
    ]
    _add_ratios(records)
    by = {(r["case"], r["size"]): r for r in records}
    # The fastest floor of the size is the reference.
    assert by["psf_mono", 64]["floor_ms"] == 1.0
    assert by["psf_mono", 64]["ratio"] == pytest.approx(10.0)
    assert by["fft_floor_scipy", 64]["ratio"] == pytest.approx(2.0)
    assert by["fft_floor_pyfftw", 64]["ratio"] == pytest.approx(1.0)
    assert by["psf_mono", 64]["vs_jax_fft"] == pytest.approx(2.5)
    assert by["psf_mono_grad", 64]["vs_forward"] == pytest.approx(2.5)
    assert by["psf_mono_grad", 64]["ratio"] == pytest.approx(25.0)
    assert by["psf_mono_grad", 128]["ratio"] == pytest.approx(30.0 / 8.0)
    assert by["psf_mono_grad", 128]["vs_forward"] is None
    assert by["psf_mono_grad", 128]["vs_jax_fft"] is None
    assert by["psf_mono", 256]["ratio"] is None and by["psf_mono", 256]["floor_ms"] is None
    assert by["fft_floor_scipy", 64]["vs_forward"] is None


def test_select_patterns_skip_and_fit():
    cases, fits = select([])
    assert [c.name for c in cases] == [c.name for c in CASES]
    assert fits == [*FIT_CASES, *SAMPLE_CASES, *UNKNOWN_DRAW_CASES, *BATCH_CASES]
    # A pattern brings the floors and JAX's FFT along, and leaves the fit out.
    cases, fits = select(["psf_mono"])
    names = {c.name for c in cases}
    assert {"psf_mono", "psf_mono_grad", "fft_floor_scipy", "fft_jax"} <= names
    assert "eye_raster" not in names and fits == []
    # Only the fit: no per-size cases at all.
    cases, fits = select(["fit"])
    assert cases == [] and fits == ["fit_daylight_eye", "fit_unknown_draw"]
    cases, fits = select(["unknown"])
    assert cases == [] and fits == ["fit_unknown_draw"]
    cases, fits = select(["sample"])
    assert cases == [] and fits == ["sample_daylight_eye"]
    # "batch" alone also names the quad case quad_spectral_batch (and its floors).
    cases, fits = select(["batch_population"])
    assert cases == [] and fits == ["batch_population"]
    cases, fits = select(["batch"])
    assert "quad_spectral_batch" in {c.name for c in cases} and fits == ["batch_population"]
    # Everything but the fit, the sampling and the batch.
    cases, fits = select([], ["fit", "sample", "batch_population"])
    assert fits == [] and {c.name for c in cases} == {c.name for c in CASES}
    # Skipping never drops the floors the ratios need.
    cases, _ = select(["eye"], ["fft"])
    assert {"fft_floor_scipy", "fft_jax", "eye_raster"} <= {c.name for c in cases}
    with pytest.raises(ConfigError, match=r"no benchmark case matches.*fit_daylight_eye"):
        select(["no_such_case"])
    with pytest.raises(ConfigError, match="skipped"):
        select(["psf_mono"], ["psf"])


def test_run_bench_writes_json_and_markdown_with_ratios_from_the_records(tmp_path):
    records = run_bench(["psf_mono"], tmp_path, [TINY], repeats=3, skip=["grad"])
    data = json.loads((tmp_path / "bench.json").read_text())
    assert set(data) == {"meta", "records", "fit"}
    assert data["fit"] == [] and data["records"] == records
    assert not (tmp_path / "bench.partial.json").exists()
    names = {r["case"] for r in data["records"]}
    assert {"fft_floor_scipy", "fft_jax", "psf_mono"} <= names
    assert names <= {"fft_floor_scipy", "fft_floor_pyfftw", "fft_jax", "psf_mono"}
    floor = min(r["median_ms"] for r in data["records"] if r["kind"] == "floor")
    jfft = next(r for r in data["records"] if r["case"] == "fft_jax")
    for r in data["records"]:
        assert r["median_ms"] > 0 and r["repeats"] >= 3 and r["first_call_s"] >= 0
        assert r["floor_ms"] == floor
        # The ratios are rounded to 3 decimals in the record.
        assert r["ratio"] == pytest.approx(r["median_ms"] / floor, abs=6e-4)
        assert r["vs_jax_fft"] == pytest.approx(r["median_ms"] / jfft["median_ms"], abs=6e-4)
    meta = data["meta"]
    assert meta["wall_s"] > 0 and "jax" in meta and any("`fft_jax`" in n for n in meta["notes"])
    md = (tmp_path / "bench.md").read_text()
    assert "## Ratio to the FFT floor" in md and "## All timings" in md
    assert f"| psf_mono | {TINY} |" in md and "JAX's CPU FFT" in md and "## Fit" not in md
    # A floor the machine lacks is named where the ratios are explained.
    has_pyfftw = "fft_floor_pyfftw" in names
    assert meta["not_installed"] == ([] if has_pyfftw else ["fft_floor_pyfftw"])
    assert ("Not installed for this run: `fft_floor_pyfftw`" in md) == (not has_pyfftw)
    # A fit-only rerun keeps the per-size timings and says what their run lacked.
    timed = {**meta, "not_installed": ["fft_floor_pyfftw"]}
    redrawn = runner.render_markdown(records, {**meta, "not_installed": [], "timings_from": timed})
    assert "Not installed for this run: `fft_floor_pyfftw`" in redrawn


@pytest.mark.slow
def test_run_bench_releases_each_case_s_compiled_programs(tmp_path):
    """XLA's CPU code takes memory maps per compiled function; kept for a whole run they
    passed the kernel's 65 530 maps per process and crashed it. Here 5 programs (3 cases,
    2 floors) add about 650 maps when released after each case and 3 900 when kept."""

    def maps() -> int:
        with open("/proc/self/maps") as f:
            return sum(1 for _ in f)

    before = maps()
    run_bench(
        ["psf_mono", "temporal_psf", "temporal_frame"],
        tmp_path,
        [TINY],
        repeats=3,
        skip=["grad", "wrap"],
    )
    assert maps() - before < 1500


def test_a_fit_only_run_keeps_the_timings_and_the_other_way_round(tmp_path):
    path = tmp_path / "bench.json"
    old_meta = {"date": "then", "load_1m_start": 1.0, "load_1m_end": 1.5, "wall_s": 10.0}
    timings = [_rec("psf_mono", 64, 1.0)]
    old_fit = {"case": "fit_daylight_eye", "kind": "fit", "npix": 64}
    path.write_text(json.dumps({"meta": old_meta, "records": timings, "fit": [old_fit]}))
    # Only a fit ran: the timings and their date are kept.
    new_fit = {"case": "fit_daylight_eye", "kind": "fit", "npix": 128}
    recs, fits, meta = _keep_previous(path, [], [new_fit], {"date": "now"})
    assert recs == timings and fits == [new_fit] and meta["timings_from"]["date"] == "then"
    # Only timings ran: the earlier fit is kept, the timings are the new ones.
    new_timings = [_rec("psf_mono", 64, 2.0)]
    recs, fits, meta = _keep_previous(path, new_timings, [], {"date": "now"})
    assert recs == new_timings and fits == [old_fit] and "timings_from" not in meta
    # An older list-shaped bench.json has nothing to keep.
    path.write_text(json.dumps(timings))
    assert _keep_previous(path, [], [], {}) == ([], [], {})
    _add_ratios(recs)
    md = render_markdown(recs, {"date": "now", "machine": "m", "jax": "j", **meta})
    assert "| psf_mono | 64 |" in md


def test_openmp_waits_passively_unless_the_environment_says_otherwise(monkeypatch):
    """Set before torch loads, PASSIVE is the default; a user's value and a process that
    already imported torch (OpenMP has read the variable) are left alone."""
    modules = {k: v for k, v in sys.modules.items() if k != "torch"}
    monkeypatch.setattr(sys, "modules", modules)
    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    assert torch_cases.passive_openmp() == "PASSIVE"
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")
    assert torch_cases.passive_openmp() == "ACTIVE"
    monkeypatch.delenv("OMP_WAIT_POLICY")
    monkeypatch.setitem(modules, "torch", object())
    assert torch_cases.passive_openmp() == ""
    assert "OMP_WAIT_POLICY" not in os.environ


def test_measure_stops_at_the_budget_after_the_minimum_repeats():
    timing = measure(lambda: time.sleep(0.02), repeats=1000, budget_s=0.05)
    assert 3 <= timing.repeats < 1000
    assert timing.median_ms > 0 and timing.min_ms <= timing.median_ms
    assert timing.first_call_s > 0 and math.isfinite(timing.cpu_per_wall)


def test_measure_together_alternates_the_calls_and_times_each_apart():
    calls = []

    def slow():
        calls.append("slow")
        time.sleep(0.004)

    def quick():
        calls.append("quick")

    slow_t, quick_t = measure_together((slow, quick), repeats=6)
    # Two warm-up calls each (both are quick to compile), then the pairs in turn.
    assert calls == ["slow"] * 2 + ["quick"] * 2 + ["slow", "quick"] * 6
    assert slow_t.repeats == quick_t.repeats == 6
    assert slow_t.min_ms >= 4.0 > quick_t.median_ms


def test_torch_cases_are_timed_with_their_twins_and_alone_without_them():
    by_name = {c.name: c for c in runner.CASES}
    torch_psf, twin = by_name["torch_psf"], by_name["torch_psf_jax"]
    jobs = runner._jobs([CASES[0], torch_psf, twin], [32, 64])
    assert jobs == [((CASES[0],), 32), ((torch_psf, twin), 32),
                    ((CASES[0],), 64), ((torch_psf, twin), 64)]  # fmt: skip
    assert runner._jobs([torch_psf], [32]) == [((torch_psf,), 32)]
    prog, full = by_name["quad_prog_box"], by_name["quad_prog_full_box"]
    assert runner._jobs([full, prog], [32]) == [((prog, full), 32)]


def test_cli_bench_rejects_bad_sizes_and_unknown_cases(tmp_path):
    cli = CliRunner()
    result = cli.invoke(app, ["bench", "psf_mono", "--sizes", "32,abc", "--out-dir", tmp_path])
    assert result.exit_code == 2 and "comma-separated integers" in result.output
    result = cli.invoke(app, ["bench", "psf_mono", "--sizes", "33", "--out-dir", tmp_path])
    assert result.exit_code == 2 and "even and >= 16" in result.output
    result = cli.invoke(app, ["bench", "nope", "--skip", "fit", "--out-dir", tmp_path])
    assert result.exit_code == 2 and "no benchmark case matches" in result.output
    assert not (tmp_path / "bench.json").exists()


def test_a_failing_case_is_reported_after_the_others_are_written(tmp_path, monkeypatch):
    def broken(n):
        raise ValueError(f"broken at {n}")

    bad = runner.Case("psf_broken", "pipeline", "always fails", broken)
    monkeypatch.setattr(runner, "CASES", (*CASES[:3], bad))
    with pytest.raises(RuntimeError, match=r"psf_broken \(N=32\).*broken at 32"):
        run_bench(["psf_broken"], tmp_path, [TINY], repeats=3)
    data = json.loads((tmp_path / "bench.json").read_text())
    assert {r["case"] for r in data["records"]} >= {"fft_floor_scipy", "fft_jax"}


# --------------------------------------------------------------------------------------
# the fit benchmark


DISK = "model.aperture.shapes[0].diameter_mm"


@pytest.mark.slow
def test_fit_benchmark_plumbing_on_a_small_disk(tmp_path):
    """The whole fit benchmark (both solvers, both dtypes, the report) on a disk pupil.

    The benchmark's own problem is the daylight eye; a disk compiles in seconds, where
    the eye takes minutes, and runs every line of the benchmark just the same.
    """
    config = tmp_path / "disk.toml"
    config.write_text(
        '[model]\nkind = "aperture"\nfocal_length_mm = 17.0\n\n'
        '[[model.shapes]]\nkind = "disk"\ndiameter_mm = 3.0\n\n'
        "[output]\npixel_scale_deg = 0.005\n"
    )
    problem = FitProblem(
        name="fit_small_disk",
        config_path=config,
        free=(FreeParameter(DISK, 2.0, 4.0, truth=3.0, start=3.3, short="D"),),
        summary="disk diameter, flux, background",
        window_mm=4.2,
    )
    record = run_fit_benchmark(problem, TINY, max_steps=3, scipy_max_nfev=3)
    json.dumps(record)  # JSON-ready as it is
    lm = record["invglare"]
    assert lm["compile_s"] > 0 and lm["solve_s"] > 0 and 1 <= lm["n_steps"] <= 3
    # Timed warm, like scipy: the second run of the compiled solve; the first is reported.
    assert lm["first_solve_s"] > 0 and "first run of the freshly compiled solve" in "\n".join(
        fit_markdown(record)
    )
    assert math.isfinite(lm["final_loss"]) and lm["jacobian_ms"] > 0
    for key in ("scipy_float64", "scipy_float32_default_step", "scipy_float32_eps32_step"):
        run = record[key]
        assert run["n_evaluations"] >= 1 and math.isfinite(run["final_loss"])
        assert run["final_loss"] <= run["start_loss"] and run["residual_ms"] > 0
        assert set(run["values"]) == set(record["problem"]["truth"])
    assert record["float32_target_loss"] > record["float32_reference_loss"] > 0
    # The target is the better float64 loss, so at least one solver reached it.
    assert record["target_loss"] >= min(lm["final_loss"], record["scipy_float64"]["final_loss"])
    assert lm["time_to_target_s"] is not None or (
        record["scipy_float64"]["time_to_target_s"] is not None
    )
    assert set(record["ratios"]) == {
        "time_to_target",
        "full_solve",
        "with_compile",
        "per_iteration_cost",
    }
    assert record["problem"]["truth"] == {DISK: 3.0, "obs.flux": 1e7, "obs.background": 20.0}
    md = "\n".join(fit_markdown(record))
    assert "## Fit: fit_small_disk" in md and "scipy trf" in md and "float32" in md
    assert "Free: disk diameter, flux, background; truth D 3, flux 1e+07, bg 20" in md


# --------------------------------------------------------------------------------------
# the sampling benchmark


def _fit_cli_helpers():
    """`invoke`, `make_problem` and `write_fit` of tests/fit/test_fit_cli.py (its small disk
    fit), loaded from its file so that tests/bench also runs on its own."""
    path = Path(__file__).resolve().parents[1] / "fit" / "test_fit_cli.py"
    module = sys.modules.get("test_fit_cli")
    if module is None:
        spec = importlib.util.spec_from_file_location("test_fit_cli", path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    return module.invoke, module.make_problem, module.write_fit


@pytest.mark.slow
def test_sample_benchmark_times_batched_and_per_walker_steps_of_a_fit(tmp_path):
    """A small disk fit, then emcee steps of its posterior in every mode; with a committed
    chain's tau, the effective samples per second follow from the step time."""
    from invglare.bench.sample import run_sample_benchmark, sample_markdown

    invoke, make_problem, write_fit = _fit_cli_helpers()

    make_problem(tmp_path)
    config = write_fit(tmp_path)
    config.write_text('[fit]\nout_dir = "report"\n' + config.read_text())
    with pytest.raises(ConfigError, match="run invglare fit"):
        run_sample_benchmark(n_steps=1, config_path=config)
    assert invoke("fit", config, "--no-progress").exit_code == 0
    posterior = tmp_path / "report" / "posterior"
    posterior.mkdir()
    taus = {"a": {"tau": 20.0}, "b": {"tau": 40.0}}
    (posterior / "summary.json").write_text(
        json.dumps({"parameters": taus, "n_walkers": 32, "n_steps": 3000})
    )
    record = run_sample_benchmark(n_steps=2, config_path=config, batches=(16, 4))
    json.dumps(record)
    assert record["tau_max"] == 40.0 and record["n_walkers"] == 32 and record["photo"] == [64, 64]
    modes = [(m["mode"], m["batch_size"]) for m in record["modes"]]
    assert modes == [("vectorize on", 16), ("vectorize on", 4), ("vectorize off", None)]
    for m in record["modes"]:
        assert m["step_ms"] >= m["min_step_ms"] > 0 and m["first_step_s"] > 0
        assert m["walker_eval_ms"] == pytest.approx(m["step_ms"] / 32)
        assert m["effective_samples_per_s"] == pytest.approx(32 / (40.0 * m["step_ms"] / 1e3))
    parts = {p["part"]: p for p in record["walker_parts"]}
    assert list(parts) == [
        "model PSF",
        "observation (shift, flux, background)",
        "pixel likelihood",
        "whole walker (log-probability)",
    ]
    assert all(p["ms"] >= p["min_ms"] > 0 for p in parts.values())
    assert parts["whole walker (log-probability)"]["share"] == 1.0
    md = "\n".join(sample_markdown(record))
    assert "## Sampling: sample_daylight_eye (64x64 photo)" in md and "tau_max = 40.0" in md
    assert "| vectorize off | — |" in md
    assert "| model PSF |" in md and "| whole walker (log-probability) |" in md and "100%" in md


def test_veiling_bench_series_and_direct_draw_the_same_ghosts():
    """The ghost-count cases compare like with like: the series image (the fraction of the
    light per pixel, averaged over the pixel) is the direct raster (sr^-1) integrated over
    each pixel, here from 5 x 5 samples per pixel times their solid angle."""
    from invglare.bench.veiling_cases import FIELD_DEG, VEILING_CASES, _ghost_arrays

    by_name = {c.name: c for c in VEILING_CASES}
    n, sub = 64, 5
    series = np.asarray(by_name["veiling_K10_H256"].make(n)(), dtype=np.float64)
    fine = np.asarray(by_name["veiling_direct_K10"].make(sub * n)(), dtype=np.float64)
    # Fine pixel i is centred at (i - sub n / 2) d / sub, so pixel k holds the fine pixels
    # sub k - 2 ... sub k + 2 (the first two of pixel 0 lie outside the fine raster: the
    # field's edge, where no ghost reaches).
    h = sub // 2
    fine = np.pad(fine, ((h, 0), (h, 0)))[: sub * n, : sub * n]
    direct = fine.reshape(n, sub, n, sub).sum(axis=(1, 3)) * np.radians(FIELD_DEG / (sub * n)) ** 2
    assert series.shape == direct.shape == (n, n)
    # The light, in closed form (every ghost lies inside the 40 deg field): a blurred disk
    # keeps the disk's area, pi R²; the direct edge, an erfc across the rim (a blurred
    # half-plane), adds its blur's second moment, pi (R² + sigma²), 0.15 % more here.
    a = _ghost_arrays(10)
    deg2 = np.radians(1.0) ** 2
    radius, soft, intensity = a["radius_deg"], a["softness_deg"], a["intensity_per_sr"]
    assert np.all(np.abs(a["position_deg"]).max(axis=1) + radius < FIELD_DEG / 2)
    assert series.sum() == pytest.approx(np.sum(intensity * np.pi * radius**2) * deg2, rel=1e-5)
    area = np.pi * (radius**2 + soft**2)
    assert direct.sum() == pytest.approx(np.sum(intensity * area) * deg2, rel=1e-5)
    # The picture: what remains is the direct edge's shape (the half-plane's, not the
    # disk's: its error grows with softness / radius) and the series' 256 harmonics:
    # 1.18 % relative L2 measured (7.8 % against pixel-centre samples, 1.5 % from 3 x 3
    # samples, 1.07 % from 9 x 9).
    rel_l2 = np.linalg.norm(series - direct) / np.linalg.norm(direct)
    assert rel_l2 < 0.013, rel_l2
    # The brightest pixel lies inside overlapping ghosts, away from every edge: equal up to
    # float32 rounding (6e-6 measured).
    assert series.max() == pytest.approx(direct.max(), rel=2e-5)


@pytest.mark.slow
def test_batch_benchmark_times_warm_clusters_of_1_and_2_workers(tmp_path):
    """Three small disk photos (one warms the workers): photos per minute on 1 and 2
    workers, the per-photo overhead of a task, and --vmap 2 with the values it fitted."""
    from helpers import disk_population

    from invglare.bench.batch import batch_markdown, run_batch_benchmark

    disk_population(tmp_path, size=3)
    with pytest.raises(ConfigError, match="has 3 photos; it needs 3 and one"):
        run_batch_benchmark(n_photos=3, config_path=tmp_path / "fit.toml",
                            photo_dir=tmp_path / "crowd")  # fmt: skip
    # The workers' compile cache: conftest's shared folder, where the fit-batch tests'
    # workers leave the same disk fit (the clock starts after each worker's warm-up fit).
    record = run_batch_benchmark(
        n_photos=2, workers=(1, 2), vmap=2, config_path=tmp_path / "fit.toml",
        photo_dir=tmp_path / "crowd", cache_dir=os.environ.get("JAX_COMPILATION_CACHE_DIR"),
    )  # fmt: skip
    json.dumps(record)
    one, two = record["clusters"]
    assert (one["workers"], two["workers"]) == (1, 2) and one["speedup"] == 1.0
    for c in (one, two):
        assert c["photos_per_min"] == pytest.approx(60 * 2 / c["wall_s"])
    assert two["speedup"] == pytest.approx(two["photos_per_min"] / one["photos_per_min"])
    assert one["task_s_per_photo"] == pytest.approx(one["wall_s"] / 2)
    assert one["overhead_s_per_photo"] == pytest.approx(
        one["task_s_per_photo"] - one["direct_s_per_photo"]
    )
    assert one["direct_s_per_photo"] > 0 and one["vmap"] == 2
    assert one["vmap_max_rel_diff"] < 1e-6  # the same optima, batched arithmetic
    md = "\n".join(batch_markdown(record))
    assert "## Batch fits on Dask: batch_population" in md and "| 2 |" in md
    assert "overhead per photo" in md and "`--vmap 2`" in md
