"""The CIE fitting study (`invglare.cie_study`, `invglare regress --cie`): the eye's radial
GSF fitted to a synthetic eye's and to the CIE's, the report, and bad specs and setups.

The tests use a tiny setup (a 96-sample pupil, 36² output pixels) that compiles once for
all of them.
"""

import dataclasses
import json

import jax
import numpy as np
import pytest
from typer.testing import CliRunner

from invglare.cie_study import (
    CieFitSetup,
    Population,
    RadialBins,
    build_fit_model,
    cie_target,
    fit_cie,
    fit_radial_gsf,
    model_gsf,
    parse_cie_spec,
    write_cie_report,
)
from invglare.cli import app
from invglare.errors import ConfigError, PhysicsRangeError

runner = CliRunner()


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


TINY = CieFitSetup(
    populations=(Population("cornea", 400, 150.5, 0.02, 0.1, 0.045, region_radius_mm=1.6),),
    aperture_npix=96,
    npix=36,
    pixel_scale_deg=0.02,
    n_bins=6,
    n_starts=3,
    max_steps=40,
)
TRUTH = {"aperture.particles[0].count": 100.4, "aperture.particles[0].radius_mean_mm": 0.062}


@pytest.mark.slow
def test_fit_recovers_a_synthetic_eye():
    with jax.enable_x64(True):
        model, space = build_fit_model(TINY)
        bins = RadialBins.build(
            TINY.npix, TINY.pixel_scale_deg, TINY.theta_min_deg, TINY.max_angle_deg(), TINY.n_bins
        )
        target = np.asarray(model_gsf(space.apply(model, space.values_from(TRUTH)), bins))
    result = fit_radial_gsf(target, TINY, label="recovery")
    for path, value in TRUTH.items():
        assert result.values[path] == pytest.approx(value, rel=0.02), path
    assert result.rms_log10 < 0.01
    # The first start is 50 % off in count and 27 % in radius.
    assert result.initial_gsf.shape == target.shape
    assert np.max(np.abs(np.log10(result.initial_gsf / target))) > 0.1


def test_cie_fit_runs_and_reports(tmp_path):
    result = fit_cie(25.0, 0.5, TINY)
    assert result.theta_deg[0] == pytest.approx(0.11, abs=0.01)
    assert result.theta_deg[-1] < TINY.max_angle_deg() < TINY.alias_free_deg()
    assert np.all(np.isfinite(result.residual_log10))
    # The residual is the log ratio of the model's GSF to the CIE target.
    np.testing.assert_allclose(
        result.residual_log10, np.log10(result.model_gsf / result.target_gsf), atol=1e-9
    )
    # This one-population eye on a 96-sample pupil reaches 0.064 log10 rms (a factor 1.16;
    # 0.106 at worst) from a first start at 0.45; the bundled 256-sample, two-population
    # fits reach 0.040. The bound leaves 25 % for another CPU's round-off along the
    # solver's path; the second shows the fit did the work, not the start.
    initial_rms = float(np.sqrt(np.mean(np.log10(result.initial_gsf / result.target_gsf) ** 2)))
    assert result.rms_log10 < 0.08, result.rms_log10
    assert result.rms_log10 < 0.25 * initial_rms, (result.rms_log10, initial_rms)
    assert 0.0 < result.energy_beyond < 1.0
    path = write_cie_report([result, result], tmp_path)
    text = path.read_text()
    assert "| 25 | 0.5 |" in text and "alias-free" in text
    assert (path.parent / "cie_A25_p0_5.png").read_bytes()[:4] == b"\x89PNG"
    assert (path.parent / "cie_all.png").is_file()
    saved = json.loads((path.parent / "fits.json").read_text())
    assert saved[0]["values"] == pytest.approx(result.values)


def test_cie_target_matches_the_formula_at_pixel_centres():
    bins = RadialBins.build(36, 0.02, 0.1, 0.34, 6)
    from invglare.reference.cie import cie_gsf

    values = np.asarray(cie_gsf(bins.pixel_theta_deg.ravel(), 70.0, 1.0, extrapolate=True))
    for k in (0, 5):
        pixels = bins.index == k
        assert cie_target(70.0, 1.0, bins)[k] == pytest.approx(values[pixels].mean(), rel=1e-6)


@pytest.mark.parametrize(
    "spec, error, message",
    [
        ("25", ConfigError, "AGE,PIGMENT"),
        ("25,abc", ConfigError, "AGE,PIGMENT"),
        ("150,0.5", PhysicsRangeError, "age = 150"),
        ("25,2", PhysicsRangeError, "pigmentation = 2"),
    ],
)
def test_bad_cie_spec_is_named(spec, error, message):
    with pytest.raises(error, match=message):
        parse_cie_spec(spec)


def test_bad_cie_setup_and_target():
    with pytest.raises(PhysicsRangeError, match="theta_max_deg"):
        CieFitSetup(theta_max_deg=5.0).validate()
    with pytest.raises(PhysicsRangeError, match="3 pixels"):
        CieFitSetup(theta_min_deg=0.05).validate()
    with pytest.raises(ConfigError, match="finite values > 0"):
        fit_radial_gsf(np.full(TINY.n_bins, np.nan), TINY)
    with pytest.raises(ConfigError, match="shape"):
        fit_radial_gsf(np.ones(3), TINY)
    result = invoke("regress", "--cie", "25;0.5")
    assert result.exit_code == 2 and "AGE,PIGMENT" in result.output


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2])
def test_fit_of_another_draw_carries_the_scatter_between_eyes_in_its_errors(seed):
    """A synthetic eye whose particles were drawn with another seed than the model's: the
    fit misses count and radius by 8-16 % and 7-12 % (the speckle of two draws differs),
    and with 32 simulated eyes its standard errors (7-9 %) include that scatter: the truth
    lies within 3 of them (measured pulls +1.1 to +1.8 for the count, -1.2 to -2.0 for the
    radius, seeds 1 and 2)."""
    setup = dataclasses.replace(TINY, draws=32)
    with jax.enable_x64(True):
        model, space = build_fit_model(dataclasses.replace(TINY, seed=seed))
        bins = RadialBins.build(
            TINY.npix, TINY.pixel_scale_deg, TINY.theta_min_deg, TINY.max_angle_deg(), TINY.n_bins
        )
        target = np.asarray(model_gsf(space.apply(model, space.values_from(TRUTH)), bins))
    result = fit_radial_gsf(target, setup, label=f"draw {seed}")
    assert result.draw_sd_log10.shape == (TINY.n_bins,) and np.all(result.draw_sd_log10 > 0)
    for path, value in TRUTH.items():
        err = result.stderr[path]
        assert 0.03 * value < err < 0.2 * value, (path, err)
        assert abs(result.values[path] - value) < 3.0 * err, (path, result.values[path], err)
    assert "between eyes" in result.summary()
