"""Golden regression (`invglare regress`, `invglare.regress`).

The whole golden suite runs once (a module fixture, about a minute of CPU, mostly XLA
compilation); the perturbation, CLI and update tests reuse its compiled programs or the
cheapest case.
"""

import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from invglare.cli import app
from invglare.errors import ConfigError, InputDataError
from invglare.files.exr import read_exr, write_exr
from invglare.regress import (
    CASES,
    DEFAULT_TOLERANCE,
    Case,
    compare_psfs,
    compute_case,
    golden_path,
    log_scaled,
    run_suite,
    select_cases,
    update_goldens,
    write_report,
)

GOLDEN = Path(__file__).resolve().parents[1] / "golden"
runner = CliRunner()
CASE = {c.name: c for c in CASES}


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


def perturbed(name: str, edit, suffix: str = "perturbed"):
    """A copy of case `name` whose config `edit` changes in place (same golden file name)."""
    import copy
    import dataclasses

    case = CASE[name]
    config = copy.deepcopy(case.config)
    edit(config)
    return dataclasses.replace(case, config=config, description=f"{case.description} ({suffix})")


@pytest.fixture(scope="module")
def suite():
    return run_suite(golden_dir=GOLDEN, progress=False)


# ------------------------------------------------------------------------------ the suite


def test_every_case_matches_its_golden(suite):
    assert [r.case.name for r in suite] == [c.name for c in CASES]
    failing = {r.case.name: r.failures for r in suite if not r.passed}
    assert not failing
    # The stored headers describe the models the registry builds now.
    assert {r.case.name: r.config_changes for r in suite if r.config_changes} == {}


def test_suite_covers_every_model_and_mode(suite):
    seen = set()
    for r in suite:
        table = r.case.config["model"]
        prop = r.model.propagator
        seen.add((table["kind"], "method", prop.method))
        seen.add((table["kind"], "propagation", prop.propagation))
        spec = r.model.spectrum
        seen.add((table["kind"], "spectral", spec.spectral if spec.is_spectral else "mono"))
        for key in ("masking", "colour"):
            if key in table:
                seen.add((table["kind"], key, table[key]))
        if table["kind"] == "camera":
            seen.add(("camera", "filter", "cross_screen" in table["camera"]))
    expected = {
        ("aperture", "method", "fft"),
        ("aperture", "method", "mft"),
        ("aperture", "propagation", "fresnel"),
        ("aperture", "spectral", "mono"),
        ("aperture", "spectral", "exact"),
        ("aperture", "spectral", "scaled"),
        ("eye", "masking", "fixed"),
        ("eye", "masking", "position"),
        ("eye", "colour", "paper_rgb"),
        ("eye", "colour", "spectral"),
        ("camera", "filter", True),
        ("temporal", "propagation", "fresnel"),
        ("temporal", "spectral", "scaled"),
    }
    assert expected <= seen
    assert all(max(r.psf.shape[:2]) <= 128 for r in suite)


def test_report_table_and_difference_images(suite, tmp_path):
    path = write_report(suite, tmp_path, golden_dir=GOLDEN)
    text = path.read_text()
    assert "**all cases pass**" in text
    assert "log-scaled" in text and "temporal" in text
    for r in suite:
        assert f"[{r.case.name}](regression/{r.case.name}.png) | pass |" in text
        png = tmp_path / "regression" / f"{r.case.name}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_one_percent_larger_pupil_fails(suite):
    def wider(config):
        config["model"]["shapes"][0]["diameter_mm"] *= 1.01

    def wider_eye(config):
        config["model"]["eye"]["pupil"]["diameter_mm"] *= 1.01

    cases = [
        perturbed("aperture_mft_mono", wider),
        perturbed("eye_position_spectral", wider_eye),
        perturbed("aperture_fft_mono", wider),
    ]
    mft, eye, fft = run_suite(golden_dir=GOLDEN, cases=cases, progress=False)
    for r in (mft, eye):
        assert r.status == "fail", r.case.name
        # Far outside float32 round-off, not a borderline call.
        assert r.metrics.rel_l2 > 100 * r.case.tolerance.rel_l2
        assert r.metrics.ssim_log < r.case.tolerance.ssim_log
        assert any(f.startswith("rel_l2") for f in r.failures)
        assert r.config_changes  # the header shows what moved
    # On the FFT's native grid the window grows with the pupil: the same array at a 1 %
    # finer pixel scale. The pixels pass; the sampling does not.
    assert fft.status == "fail"
    assert fft.failures == [f for f in fft.failures if f.startswith("pixel scale")] != []


def test_golden_header_rebuilds_its_model():
    # The header alone (the full config as to_config() writes it) reproduces the PSF.
    case = CASE["aperture_mft_mono"]
    golden = read_exr(golden_path(GOLDEN, case))
    assert golden.attrs["regressionCase"] == case.name
    assert golden.config != case.config  # every default made explicit
    from_header = Case(case.name, "rebuilt from the golden's header", golden.config)
    psf, model = compute_case(from_header)
    metrics = compare_psfs(golden.data, psf, golden.pixel_scale_deg)
    assert metrics.failures(case.tolerance) == []
    assert model.to_config() == golden.config


# ------------------------------------------------------------------------------ metrics


def _gauss(n=128, sigma=3.0):
    # 128 px like the suite's PSFs: the jitted encircled energy is reused, not recompiled.
    y, x = np.mgrid[:n, :n] - n // 2
    g = np.exp(-(x * x + y * y) / (2 * sigma**2))
    return g / g.sum()


def test_metrics_of_a_known_difference():
    ref = _gauss()
    same = compare_psfs(ref, ref.copy(), 0.01)
    assert (same.rel_l2, same.max_err, same.ee_diff) == (0.0, 0.0, 0.0)
    assert same.ssim_log == pytest.approx(1.0) and math.isinf(same.psnr_db)
    m = compare_psfs(ref, 1.01 * ref, 0.01)
    assert m.rel_l2 == pytest.approx(0.01, rel=1e-9)
    assert m.max_err == pytest.approx(0.01, rel=1e-9)
    mse = np.mean((0.01 * ref) ** 2)
    assert m.psnr_db == pytest.approx(10 * np.log10(ref.max() ** 2 / mse), rel=1e-9)
    # 1 % more light everywhere: the encircled fraction grows by 1 % of itself (up to
    # 0.01 at the largest radius, to the float32 precision of the encircled energy).
    assert m.ee_diff == pytest.approx(0.01, rel=1e-4)
    assert m.failures(DEFAULT_TOLERANCE)
    with pytest.raises(InputDataError, match="shape"):
        compare_psfs(ref, ref[:-1], 0.01)


def test_log_ssim_sees_glare_far_below_the_peak():
    # A faint streak at 1e-6 of the peak: invisible to the linear metrics, which stay
    # inside the default tolerance, but a clear structural change in the log image.
    ref = _gauss() + 1e-9
    new = ref.copy()
    new[64, 72:] += 1e-6 * ref.max()
    m = compare_psfs(ref, new, 0.01)
    assert m.max_err < DEFAULT_TOLERANCE.max_err
    assert m.ssim_log < DEFAULT_TOLERANCE.ssim_log
    assert log_scaled(np.array([1.0, 1e-3, 1e-9]), 1.0).tolist() == pytest.approx([1.0, 0.5, 0.0])


def test_unknown_case_is_named():
    with pytest.raises(ConfigError, match=r"'nope'.*aperture_fft_mono"):
        select_cases(["nope"])
    result = invoke("regress", "nope")
    assert result.exit_code == 2
    assert "nope" in result.output


# ------------------------------------------------------------------------------ CLI / update


@pytest.fixture
def golden_copy(tmp_path):
    folder = tmp_path / "golden"
    folder.mkdir()
    shutil.copy(golden_path(GOLDEN, CASE["aperture_fft_mono"]), folder)
    return folder


def _scale_golden(folder: Path, factor: float) -> None:
    path = golden_path(folder, CASE["aperture_fft_mono"])
    g = read_exr(path)
    attrs = {k: v for k, v in g.attrs.items() if k != "invglareVersion"}  # write_exr's own
    write_exr(path, g.data * factor, pixel_scale_deg=g.pixel_scale_deg,
              wavelengths_nm=g.wavelengths_nm, config=g.config, attrs=attrs)  # fmt: skip


def test_cli_fails_naming_the_case(golden_copy, tmp_path):
    _scale_golden(golden_copy, 1.0001)  # 1e-4 relative: 5x the L2 tolerance
    out = tmp_path / "reports"
    result = invoke("regress", "aperture_fft_mono", "--golden-dir", golden_copy, "--out-dir", out)
    assert result.exit_code == 1
    assert "FAIL aperture_fft_mono: rel_l2" in result.output
    assert "1 of 1 case(s) failed: aperture_fft_mono" in result.output
    # One case of all: a partial report beside the full one, which it leaves alone.
    text = (out / "regression.partial.md").read_text()
    assert "| FAIL |" in text and f"a partial run of 1 of the {len(CASES)} cases" in text
    assert (out / "regression.partial" / "aperture_fft_mono.png").is_file()
    assert not (out / "regression.md").exists() and not (out / "regression").exists()


def test_cli_missing_golden_says_how_to_create_it(tmp_path):
    empty = tmp_path / "golden"
    empty.mkdir()
    result = invoke("regress", "aperture_fft_mono", "--golden-dir", empty, "--out-dir", tmp_path)
    assert result.exit_code == 1
    assert "--update --reason" in result.output


def test_update_needs_a_reason(golden_copy, tmp_path):
    result = invoke("regress", "--update", "--golden-dir", golden_copy, "--out-dir", tmp_path)
    assert result.exit_code == 2
    assert "--reason" in result.output
    result = invoke("regress", "--reason", "x", "--golden-dir", golden_copy)
    assert result.exit_code == 2
    with pytest.raises(ConfigError, match="reason"):
        update_goldens([], golden_copy, "  ")


def test_update_rewrites_and_logs_the_change(golden_copy, tmp_path):
    _scale_golden(golden_copy, 1.01)
    args = ["aperture_fft_mono", "--golden-dir", golden_copy, "--out-dir", tmp_path]
    result = invoke("regress", "--update", "--reason", "new FFT normalisation", *args)
    assert result.exit_code == 0, result.output
    log = (golden_copy / "CHANGES.md").read_text()
    assert "Reason: new FFT normalisation" in log
    row = next(line for line in log.splitlines() if line.startswith("| aperture_fft_mono"))
    assert "| failed |" in row
    # The metrics before the update: the stored PSF was 1 % too bright.
    assert float(row.split("|")[3]) == pytest.approx(0.0099, rel=0.02)
    assert invoke("regress", *args).exit_code == 0
    # Nothing differs any more: a second update rewrites nothing and says so.
    before = golden_path(golden_copy, CASE["aperture_fft_mono"]).read_bytes()
    assert invoke("regress", "--update", "--reason", "again", *args).exit_code == 0
    assert golden_path(golden_copy, CASE["aperture_fft_mono"]).read_bytes() == before
    assert (
        "Unchanged (bit-identical, not rewritten): aperture_fft_mono"
        in (golden_copy / "CHANGES.md").read_text()
    )
