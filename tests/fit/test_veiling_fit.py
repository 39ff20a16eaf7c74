"""Fitting veiling glare: the light's direction as a model leaf, the ghost report, and
``invglare fit`` on a synthetic veiling frame (the issue's recovery: every ghost's
intensity within 5 % and position within 0.5 px, from 3 starts)."""

import json
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import central_difference, x64
from typer.testing import CliRunner

from invglare.cli import app
from invglare.config.model import build_model
from invglare.errors import PhysicsRangeError
from invglare.files.toml import load_toml
from invglare.fit.ghost_report import ghost_section
from invglare.models.veiling import GhostSet, VeilingGlare

runner = CliRunner()

GHOSTS = """
[model]
kind = "veiling"
profile = "disk"
n_harmonics = 24
light_angle_deg = [0.0, 0.0]

[model.ghosts]
position_deg = [[0.0, 0.0], [0.0, 0.0], [0.0, 0.0]]
radius_deg = [1.5, 2.5, 4.0]
intensity_per_sr = [0.03, 0.01, 0.004]
softness_deg = 0.25
ratio = [-0.6, 0.5, -1.4]

[output]
npix = [40, 56]
pixel_scale_deg = 0.25
"""


def _model(angle=(0.0, 0.0)) -> VeilingGlare:
    ghosts = GhostSet.build(
        [[0.0, 0.0]] * 2, [1.5, 3.0], [0.02, 0.01], softness_deg=0.3, ratio=[-0.5, 0.8]
    )
    return VeilingGlare.build(
        ghosts, npix=(24, 32), pixel_scale_deg=0.4, n_harmonics=16, light_angle_deg=angle
    )


def test_the_light_angle_leaf_is_the_default_direction_and_round_trips():
    model = _model((1.5, -0.75))
    np.testing.assert_array_equal(np.asarray(model()), np.asarray(model(jnp.array([1.5, -0.75]))))
    assert not np.allclose(np.asarray(model()), np.asarray(_model()()))
    # An explicit direction still wins, and the on-axis index ignores the leaf.
    np.testing.assert_array_equal(np.asarray(model((0.0, 0.0))), np.asarray(_model()()))
    assert float(model.veiling_glare_index(1.0)) == pytest.approx(
        float(_model().veiling_glare_index(1.0)), rel=1e-6
    )
    config = model.to_config()
    assert config["model"]["light_angle_deg"] == [1.5, -0.75]
    again = build_model(config)
    np.testing.assert_array_equal(np.asarray(again.light_angle_deg), [1.5, -0.75])
    with pytest.raises(PhysicsRangeError, match=r"light_angle_deg must have shape \(2,\)"):
        _model((1.0, 2.0, 3.0))
    with pytest.raises(PhysicsRangeError, match="within"):
        _model((95.0, 0.0))


def test_gradient_through_the_light_angle_leaf_matches_finite_differences():
    """Autodiff against central differences converging over two steps (1e-3, 1e-4 deg):
    the relative error falls >= 10x (measured 2.5e-8 -> 2e-10) to below 1e-8."""
    with x64():
        model = _model((1.0, 0.5))
        w = jnp.asarray(np.random.default_rng(3).uniform(size=model.npix))

        def loss(x):
            m = eqx.tree_at(lambda m: m.light_angle_deg, model, jnp.stack([x, jnp.asarray(0.5)]))
            return jnp.sum(w * m()) / m.pixel_solid_angle_sr

        ad = float(jax.grad(loss)(1.0))
        errors = [abs(central_difference(loss, 1.0, h) - ad) / abs(ad) for h in (1e-3, 1e-4)]
        assert errors[1] <= errors[0] / 10 and errors[1] < 1e-8, errors
        assert abs(ad) > 1e-3
        # The same derivative as through the call's argument.
        arg = jax.grad(lambda x: jnp.sum(w * model(jnp.stack([x, 0.5]))))(1.0)
        assert float(arg) / model.pixel_solid_angle_sr == pytest.approx(ad, rel=1e-9)


def test_ghost_section_errors_follow_a_known_shift():
    truth = _model((1.0, 0.0))
    same, data = ghost_section(truth, truth)
    assert data["max_position_error_px"] == 0 and data["max_intensity_rel_error"] == 0
    assert len(same) == 2 + 2 + 2  # the summary, a blank, the table's head, two ghosts
    # The light 0.2 deg further right moves its image on the screen by
    # deg(tan 1.2 deg) - deg(tan 1 deg) = 0.20009 deg (0.50023 px), each ghost ratio times that.
    moved = _model((1.2, 0.0))
    _, data = ghost_section(moved, truth)
    step_px = np.degrees(np.tan(np.radians(1.2)) - np.tan(np.radians(1.0))) / 0.4
    np.testing.assert_allclose(data["position_error_px"], [0.5 * step_px, 0.8 * step_px], rtol=1e-5)
    brighter = eqx.tree_at(lambda m: m.ghosts.intensity_per_sr, truth, jnp.array([0.021, 0.01]))
    _, data = ghost_section(brighter, truth)
    np.testing.assert_allclose(data["intensity_rel_error"], [0.05, 0.0], atol=1e-6)
    lines, data = ghost_section(truth)
    assert "truth" not in data and "true intensity" not in lines[2]


@pytest.mark.slow
def test_fit_command_recovers_each_ghost_of_a_synthetic_veiling_frame(tmp_path):
    """`invglare synth` then `invglare fit` on a 56x40 veiling frame (not square)."""
    (tmp_path / "ghosts.toml").write_text(GHOSTS)
    (tmp_path / "frame.toml").write_text(
        '[synth]\nmodel = "ghosts.toml"\nseed = 2\n\n[set]\n'
        '"model.light_angle_deg[0]" = 1.6\n"model.light_angle_deg[1]" = -0.9\n'
        '"model.ghosts.intensity_per_sr[1]" = 0.013\n\n'
        "[observation]\nflux = 2e9\nbackground = 10.0\ngain = 2.0\nread_noise = 3.0\n"
    )
    result = runner.invoke(app, ["synth", str(tmp_path / "frame.toml")])
    assert result.exit_code == 0, result.output
    free = "".join(
        f'\n[[free]]\npath = "{path}"\nlower = {lo}\nupper = {hi}\n'
        for path, lo, hi in (
            ("model.light_angle_deg[0]", 0.5, 2.5),
            ("model.light_angle_deg[1]", -2.0, 0.0),
            ("model.ghosts.intensity_per_sr[0]", 0.005, 0.06),
            ("model.ghosts.intensity_per_sr[1]", 0.002, 0.03),
            ("model.ghosts.intensity_per_sr[2]", 0.001, 0.01),
        )
    )
    (tmp_path / "fit.toml").write_text(
        '[target]\nfile = "frame.exr"\n\n[model]\nconfig = "ghosts.toml"\n\n'
        "[observation]\nflux = 2e9\nbackground = 10.0\ngain = 2.0\nread_noise = 3.0\n"
        + free
        + '\n[views]\npixels = 1.0\n\n[solver]\nn_starts = 3\nmax_steps = 60\nbatch = "loop"\n'
    )
    out = tmp_path / "report"
    result = runner.invoke(
        app, ["fit", str(tmp_path / "fit.toml"), "--out-dir", str(out), "--no-progress"]
    )
    assert result.exit_code == 0, result.output
    params = json.loads((out / "params.json").read_text())
    assert params["fit"]["shape"] == [40, 56] and len(params["starts"]) == 3
    ghosts = params["ghosts"]
    assert ghosts["n_ghosts"] == 3
    assert ghosts["max_position_error_px"] < 0.5 and ghosts["max_intensity_rel_error"] < 0.05
    for path in ("model.light_angle_deg[0]", "model.ghosts.intensity_per_sr[1]"):
        entry = params["parameters"][path]
        assert abs(entry["value"] - entry["truth"]) < 4 * entry["stderr"], path
    report = (out / "report.md").read_text()
    assert "## Ghosts" in report and "position error px" in report


def test_bundled_veiling_fit_config_loads_with_its_truth():
    from invglare.config.fit import load_fit

    root = Path(__file__).resolve().parents[2]
    with x64():
        setup = load_fit(root / "fits" / "veiling_cooke.toml")
        assert setup.target.shape == (256, 384)
        assert setup.truth["model.light_angle_deg[0]"] == pytest.approx(4.0)
        truth = setup.truth_model()
    assert isinstance(truth, VeilingGlare)
    assert load_toml(root / "data_synthetic" / "veiling_cooke.toml")["set"][
        "model.ghosts.lens.sensor_reflectance"
    ] == pytest.approx(float(truth.ghosts.lens.sensor_reflectance))
