"""`invglare fit` with a reference glare function as the target ([reference]): the CIE's,
a 2-D PSF file or a 1-D GSF table; the eye's radial GSF is fitted in log units."""

import json
import textwrap
from pathlib import Path

import jax
import numpy as np
import OpenEXR
import pytest
from typer.testing import CliRunner

from invglare.cie_study import build_fit_model, photopic_psf
from invglare.cie_study.config import load_reference_fit
from invglare.cli import app
from invglare.errors import ConfigError, InputDataError, PhysicsRangeError
from invglare.files.exr import write_exr

runner = CliRunner()

#: A small eye (one particle population, 96 pupil samples): compiles in about a minute.
EYE = """
[eye]
aperture_npix = 96
npix = 36
pixel_scale_deg = 0.02

[[population]]
region = "cornea"
count_max = 400
count_init = 150.5
radius_min_mm = 0.02
radius_max_mm = 0.1
radius_init_mm = 0.045

[range]
n_bins = 6

[solver]
n_starts = 3
max_steps = 40
"""
TRUTH = {"aperture.particles[0].count": 100.4, "aperture.particles[0].radius_mean_mm": 0.062}


def write_config(folder, reference: str, extra: str = EYE):
    path = folder / "ref_fit.toml"
    path.write_text("[reference]\n" + textwrap.dedent(reference) + "\n" + extra)
    return path


def test_command_line_overrides_replace_the_configs_solver_keys(tmp_path):
    """--n-starts / --max-steps win over [solver] n_starts / max_steps, which stay valid keys
    (the override once made the reader call the config's own max_steps unknown)."""
    path = write_config(tmp_path, "cie = { age = 25, pigmentation = 1 }")
    setup = load_reference_fit(path, n_starts=1, max_steps=2).setup
    assert (setup.n_starts, setup.max_steps) == (1, 2)
    setup = load_reference_fit(path).setup
    assert (setup.n_starts, setup.max_steps) == (3, 40)


def test_a_psf_file_made_by_the_eye_is_fitted_back_to_its_parameters(tmp_path):
    """The reference is a 2-D EXR of the eye's own PSF at known particle values."""
    setup = load_reference_fit(write_config(tmp_path, "cie = { age = 25, pigmentation = 1 }")).setup
    with jax.enable_x64(True):
        model, space = build_fit_model(setup)
        psf = np.asarray(photopic_psf(space.apply(model, space.values_from(TRUTH))))
    write_exr(tmp_path / "eye_psf.exr", psf.astype(np.float32), pixel_scale_deg=0.02)
    config = write_config(tmp_path, 'file = "eye_psf.exr"')
    out = tmp_path / "report"
    result = runner.invoke(app, ["fit", str(config), "--out-dir", str(out), "--no-progress"])
    assert result.exit_code == 0, result.output
    fit = json.loads((out / "fit.json").read_text())
    for path, value in TRUTH.items():
        assert fit["values"][path] == pytest.approx(value, rel=0.05), path
    assert fit["rms_log10"] < 0.02 and fit["age"] is None
    text = (out / "report.md").read_text()
    assert "eye_psf.exr" in text and "log10(model / reference)" in text
    assert (out / "gsf.png").read_bytes()[:4] == b"\x89PNG"

    # The CIE as the reference, with the same eye (same compiled model in this process).
    config = write_config(tmp_path, "cie = { age = 50, pigmentation = 1.0 }")
    out = tmp_path / "cie"
    result = runner.invoke(app, ["fit", str(config), "--out-dir", str(out), "--no-progress"])
    assert result.exit_code == 0, result.output
    fit = json.loads((out / "fit.json").read_text())
    assert fit["age"] == 50 and fit["pigmentation"] == 1.0
    assert np.isfinite(fit["rms_log10"]) and 0 < fit["energy_beyond_fit_range"] < 1
    assert "age 50, pigmentation 1" in (out / "report.md").read_text()


def test_a_gsf_table_is_averaged_over_the_annuli_like_the_model(tmp_path):
    theta = np.geomspace(0.01, 5.0, 40)
    (tmp_path / "gsf.csv").write_text(
        "theta_deg,gsf\n" + "".join(f"{t},{1e3 * t**-2.5}\n" for t in theta)
    )
    ref = load_reference_fit(write_config(tmp_path, 'file = "gsf.csv"'))
    from invglare.cie_study import RadialBins

    s = ref.setup
    bins = RadialBins.build(s.npix, s.pixel_scale_deg, s.theta_min_deg, s.max_angle_deg(), 6)
    target = ref.target(bins)
    for k in range(6):
        pixels = bins.pixel_theta_deg.ravel()[bins.index == k]
        assert target[k] == pytest.approx(np.mean(1e3 * pixels**-2.5), rel=1e-6)
    assert "gsf.csv" in ref.describe()


@pytest.mark.parametrize(
    "reference, extra, error, match",
    [
        ("", EYE, ConfigError, "exactly one of cie"),
        ('cie = { age = 25, pigmentation = 1 }\nfile = "x.csv"', EYE, ConfigError, "exactly one"),
        ("cie = { age = 120, pigmentation = 1 }", EYE, PhysicsRangeError, "120"),
        ("cie = { age = 25 }", EYE, ConfigError, "pigmentation"),
        ("cie = { age = 25, pigmentation = 1 }", EYE + "\n[extra]\n", ConfigError, r"\[extra\]"),
        (
            "cie = { age = 25, pigmentation = 1 }",
            EYE.replace("npix = 36", "npx = 36"),
            ConfigError,
            "npx",
        ),
        (
            "cie = { age = 25, pigmentation = 1 }",
            EYE.replace("count_init = 150.5", "count_init = 500.5"),
            ConfigError,
            "count_init",
        ),
        (
            "cie = { age = 25, pigmentation = 1 }",
            EYE.replace("n_bins = 6", "n_bins = 6\ntheta_max_deg = 5.0"),
            PhysicsRangeError,
            "alias-free",
        ),
        ('file = "missing.csv"', EYE, InputDataError, "missing.csv"),
        ('file = "short.csv"', EYE, InputDataError, "covers"),
        ('file = "backwards.csv"', EYE, InputDataError, "increasing"),
        ('file = "no_scale.exr"', EYE, InputDataError, "pixelScaleDeg"),
    ],
    ids=[
        "neither",
        "both",
        "age",
        "no-pigmentation",
        "unknown-section",
        "unknown-key",
        "count-init",
        "beyond-alias-free",
        "missing-file",
        "short-table",
        "backwards-table",
        "exr-without-scale",
    ],
)
def test_bad_reference_configs_name_the_problem(tmp_path, reference, extra, error, match):
    (tmp_path / "short.csv").write_text("0.05,100\n0.1,20\n")  # stops before the range does
    (tmp_path / "backwards.csv").write_text("0.1,20\n0.05,100\n1.0,1\n")
    # write_exr always stores the pixel scale: a bare file is written with OpenEXR itself.
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"Y": np.ones((8, 8), np.float32)}) as exr:
        exr.write(str(tmp_path / "no_scale.exr"))
    with pytest.raises(error, match=match):
        load_reference_fit(write_config(tmp_path, reference, extra))


ROOT = Path(__file__).resolve().parents[2]


def test_committed_cie_fits_cover_every_age_and_pigmentation_within_the_stated_residual():
    """reports/cie (invglare regress --cie) and reports/cie_A50_p1 (invglare fit)."""
    fits = json.loads((ROOT / "reports" / "cie" / "fits.json").read_text())
    pairs = {(f["age"], f["pigmentation"]) for f in fits}
    assert pairs == {(a, p) for a in (25.0, 50.0, 70.0) for p in (0.5, 1.0)}
    for f in fits:
        # The README's stated residuals: 0.045 rms and 0.102 at worst (age 70, p = 1).
        assert f["converged"] and f["rms_log10"] < 0.05 and f["max_log10"] < 0.11, f["label"]
        assert f["theta_deg"][0] < 0.11 and f["theta_deg"][-1] > 0.9
    single = json.loads((ROOT / "reports" / "cie_A50_p1" / "fit.json").read_text())
    same = next(f for f in fits if (f["age"], f["pigmentation"]) == (50.0, 1.0))
    # Both commands run the same fit: same setup, same result.
    assert single["values"] == pytest.approx(same["values"], rel=1e-6)
    ref = load_reference_fit(ROOT / "fits" / "cie_A50_p1.toml")
    assert ref.cie == (50.0, 1.0) and ref.out_dir == Path("runs") / "cie_A50_p1"
