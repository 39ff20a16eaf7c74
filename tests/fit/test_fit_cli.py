"""`invglare fit`: configs, reports, bad input, Ctrl-C, and recovery on the bundled photos.

The mechanics run on a 64 x 64 disk photo made by `invglare synth` (cheap to compile);
the recovery tests (slow) run the bundled fit configs on the bundled photos and check
the issue's tolerances. Fits run in float64 (the command enables it itself).
"""

import json
import logging
import math
import re
import shutil
import warnings
from pathlib import Path

import equinox as eqx
import numpy as np
import OpenEXR
import pytest
from typer.testing import CliRunner

from invglare.cli import app
from invglare.config.fit import load_fit
from invglare.errors import ConfigError, InputDataError
from invglare.files.exr import read_exr, write_exr
from invglare.files.images import write_png
from invglare.files.toml import load_toml
from invglare.fit.params import START_MARGIN

ROOT = Path(__file__).resolve().parents[2]
FITS = ROOT / "fits"
runner = CliRunner()
DIAMETER = "model.aperture.shapes[0].diameter_mm"

DISK_MODEL = """
[model]
kind = "aperture"
focal_length_mm = 17.0
aperture_npix = 64
window_mm = 5.4

[[model.shapes]]
kind = "{kind}"
diameter_mm = 3.5{extra}

[output]
npix = 64
pixel_scale_deg = 0.0035

[spectrum]
wavelengths_nm = 550
"""

SPEC = """
[synth]
model = "model.toml"
seed = 5
out = "photo"

[set]
"model.aperture.shapes[0].diameter_mm" = 3.0

[observation]
flux = 1e6
background = 20.0
dx_px = 0.3
dy_px = -0.2
gain = 2.0
read_noise = 3.0
saturation = 30000.0
"""

FIT = """
[target]
file = "{target}"
saturation = 30000.0{target_extra}

[model]
config = "model.toml"

[observation]
gain = 2.0
read_noise = 3.0
{free}
[[free]]
path = "obs.flux"
lower = 0.0
upper = inf

[[free]]
path = "obs.background"
lower = -100.0
upper = 1000.0

[[free]]
path = "obs.dx_px"
lower = -2.0
upper = 2.0

[[free]]
path = "obs.dy_px"
lower = -2.0
upper = 2.0

[solver]
n_starts = 3
max_steps = 80
{solver_extra}"""

FREE_DIAMETER = f"""
[[free]]
path = "{DIAMETER}"
lower = 2.0
upper = 5.0
"""


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


def stratum(x: float, lower: float, upper: float, n: int = 3) -> int:
    """Which of `n` strata of the start sampler (bounds less its margins) holds `x`."""
    u = ((x - lower) / (upper - lower) - START_MARGIN) / (1 - 2 * START_MARGIN)
    return min(int(n * u), n - 1)


def make_problem(folder: Path, kind: str = "disk", extra: str = "") -> Path:
    """A 64 x 64 synthetic photo (diameter 3.0 mm, clipped core) and its model config."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "model.toml").write_text(DISK_MODEL.format(kind=kind, extra=extra))
    (folder / "spec.toml").write_text(SPEC)
    result = invoke("synth", folder / "spec.toml")
    assert result.exit_code == 0, result.output
    return folder / "photo.exr"


def write_fit(folder: Path, target: str = "photo.exr", **parts) -> Path:
    text = FIT.format(
        target=target,
        target_extra=parts.get("target_extra", ""),
        free=parts.get("free", FREE_DIAMETER),
        solver_extra=parts.get("solver_extra", ""),
    )
    path = folder / parts.get("name", "fit.toml")
    path.write_text(text + parts.get("tail", ""))
    return path


@pytest.fixture(scope="module")
def disk(tmp_path_factory):
    folder = tmp_path_factory.mktemp("disk")
    make_problem(folder)
    return folder


STAGE = """
[[stage]]
views = { radial = 1.0 }
max_steps = 30
"""


@pytest.fixture(scope="module")
def disk_report(disk):
    """The disk fit run once through the CLI, radial profile first, then pixel by pixel:
    (folder, params.json, report.md text)."""
    config = write_fit(disk, tail=STAGE)
    out = disk / "report"
    result = invoke("fit", config, "--out-dir", out, "--no-progress")
    assert result.exit_code == 0, result.output
    return out, json.loads((out / "params.json").read_text()), (out / "report.md").read_text()


# --------------------------------------------------------------------------------------
# the report


def test_the_first_line_names_every_stages_views():
    """'views radial, angular then pixels' for fits/eye_daylight.toml, not 'views pixels'."""
    from invglare.commands.fit import views_in_order
    from invglare.fit.stages import Stage

    stage = Stage({"radial": 1.0, "angular": 1.0}, 40)
    assert views_in_order([stage], {"pixels": 1.0}) == "radial, angular then pixels"
    assert views_in_order([], {"pixels": 1.0, "log": 0.5}) == "pixels, log"


@pytest.mark.slow
def test_fit_report_files_and_recovery_with_clipped_core(disk_report):
    """Clipped core (survival-censored), 3 starts across [2, 5] mm: diameter within 0.5 %."""
    out, params, text = disk_report
    for name in ("report.md", "params.json", "images.png", "profiles.png", "loss.png"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".report")]
    entry = params["parameters"][DIAMETER]
    assert set(entry) >= {"value", "stderr", "truth"} and entry["truth"] == pytest.approx(3.0)
    assert abs(entry["value"] - 3.0) < 0.005 * 3.0
    assert abs(entry["value"] - 3.0) < 5 * entry["stderr"]
    assert params["parameters"]["obs.dx_px"]["truth"] == pytest.approx(0.3)
    assert params["converged"] and 0.8 < params["reduced_chi2"] < 1.25
    starts = sorted(s[DIAMETER] for s in params["starts"])
    assert len(starts) == 3 and starts[0] < 3.0 < starts[-1]
    assert params["fit"]["saturation"] == 30000.0 and params["fit"]["shape"] == [64, 64]
    assert "| `model.aperture.shapes[0].diameter_mm` |" in text and "| mm |" in text
    assert "reduced χ²" in text and "compile" in text and "solve" in text
    assert "pixels clipped at 30000" in text and "![images.png](images.png)" in text
    # Two stages on record: 3 starts on the radial profile, then the best one pixel-wise.
    first, last = params["stages"]
    assert first["views"] == {"radial": 1.0} and len(first["final_loss"]) == 3
    assert last["views"] == {"pixels": 1.0} and len(last["final_loss"]) == 1
    assert last["origin"] == [params["best_start"]] and first["best"] == params["best_start"]
    assert "1) radial 1 → 2) pixels 1" in text
    # The final stage maximised the likelihood, at its optimum; the report leads with that.
    assert params["objective"].startswith("the Poisson–Gaussian likelihood of the pixels")
    assert params["optimum_check"]["gain"] < 0.5 and params["covariance_scale"] == 1.0
    assert params["flags"] == [] and "> **No flags:** at the likelihood's optimum" in text
    assert text.index("No flags") < text.index("## Result")


def test_load_fit_setup_is_a_clean_public_object(disk):
    setup = load_fit(write_fit(disk), out_dir=disk / "x")
    assert setup.target.shape == (64, 64) and setup.target.dtype == np.float64
    assert setup.pixel_scale_deg == pytest.approx(0.0035)
    assert setup.space.paths[0] == DIAMETER and setup.starts.shape == (3, 5)
    assert setup.truth[DIAMETER] == pytest.approx(3.0) and setup.truth["obs.flux"] == 1e6
    assert setup.forward.obs.saturation == 30000.0 and setup.views == {"pixels": 1.0}
    kwargs = setup.fit_kwargs()
    assert kwargs["n_starts"] == 3 and kwargs["max_steps"] == 80 and kwargs["solver"] == "lm"
    # Nuisance starts sit at the guesses from the photo (the centre from the clipped core,
    # truth (0.3, -0.2)); the diameter's are spread over thirds of its bounds.
    assert np.all(setup.starts[:, 3] == setup.starts[0, 3]) and np.all(
        setup.starts[:, 4] == setup.starts[0, 4]
    )
    assert abs(setup.starts[0, 3] - 0.3) < 0.15 and abs(setup.starts[0, 4] + 0.2) < 0.15
    assert sorted(stratum(x, 2.0, 5.0) for x in setup.starts[:, 0]) == [0, 1, 2]
    assert setup.out_dir == disk / "x" and setup.candidates() == [{}]


def test_init_range_draws_starts_inside_it(disk):
    free = FREE_DIAMETER + "init = [2.6, 2.9]\n"
    setup = load_fit(write_fit(disk, free=free, name="range.toml"))
    d = np.sort(setup.starts[:, 0])
    assert np.all((d > 2.6) & (d < 2.9)) and d[0] < 2.7 and d[-1] > 2.8


# --------------------------------------------------------------------------------------
# pixel scale and discrete choices


SCALE = "model.propagator.output.pixel_scale_deg"
RATIO = "obs.pixel_scale_ratio"


@pytest.mark.parametrize(
    ("path", "scale", "tol"),
    [(RATIO, 0.0042, 0.03), (RATIO, 0.0028, 0.03), (SCALE, 0.0042, 0.002)],
    ids=["ratio+20%", "ratio-20%", "exact+20%"],
)
@pytest.mark.slow
def test_wrong_pixel_scale_is_recovered_when_free(disk, path, scale, tol):
    """The model is built at a pixel scale 20 % off the photo's (0.0035 deg/px) and the fit
    starts there (a nuisance: every start): it converges to the photo's scale.

    - ``obs.pixel_scale_ratio`` (model scale / photo scale, truth 1.2 or 0.8) magnifies the
      model's PSF by bilinear resampling, which blurs an Airy core of 3 px: within 3 %.
    - ``model.propagator.output.pixel_scale_deg`` (truth 0.0035) recomputes the matrix
      Fourier transform at the fitted scale, exactly: within 0.2 %.

    The diameter is fixed at its truth here: for a lone disk, diameter and pixel scale
    change the PSF the same way (its size scales with 1 / (diameter * scale)). From the
    one start 20 % off, the pixels go first in the generalised-Anscombe domain, whose
    basin is wider here (the likelihood alone, from a model 25 % too small, ended at a
    ratio of 1.075, reduced chi-square 128); the fit ends on the likelihood, and the
    report says so. The resampled core misfits the photo (reduced chi-square ~8 for 0.8):
    the report flags it, naming the model as the likely cause.
    """
    (disk / "model_fixed.toml").write_text(
        DISK_MODEL.format(kind="disk", extra="").replace("3.5", "3.0")
    )
    bounds = (0.7, 1.5) if path == RATIO else (0.0025, 0.005)
    free = f"""
[[free]]
path = "{path}"
lower = {bounds[0]}
upper = {bounds[1]}
nuisance = true
"""
    text = write_fit(
        disk, free=free, target_extra=f"\npixel_scale_deg = {scale}", name="scale.toml"
    ).read_text()
    config = disk / "scale.toml"
    text = text.replace('config = "model.toml"', 'config = "model_fixed.toml"')
    config.write_text(text + '\n[view_options.pixels]\ndomain = "anscombe"\n')
    out = disk / "scale_report"
    result = invoke("fit", config, "--out-dir", out, "--no-progress", "--n-starts", 1)
    assert result.exit_code == 0, result.output
    params = json.loads((out / "params.json").read_text())
    entry = params["parameters"][path]
    truth = scale / 0.0035 if path == RATIO else 0.0035
    wrong = 1.0 if path == RATIO else scale
    assert entry["truth"] == pytest.approx(truth)
    assert params["starts"][0][path] == pytest.approx(wrong)  # 20 % off
    assert params["converged"]
    assert abs(entry["value"] - truth) < tol * truth
    assert abs(params["parameters"]["obs.dx_px"]["value"] - 0.3) < 0.03
    assert params["objective"].endswith("refined from a first pass in the anscombe domain")
    assert [st.get("likelihood") for st in params["stages"]] == [False, True]
    if path == RATIO:
        chi2 = [f for f in params["flags"] if f["kind"] == "reduced_chi2"]
        assert chi2 and chi2[0]["cause"] == "model_misfit", params["flags"]


BLADES = "model.aperture.shapes[0].n_blades"


@pytest.fixture(scope="module")
def hexagon(tmp_path_factory):
    """A 64 x 64 photo of a hexagonal stop (6 blades, rotated 10 deg) and its model config."""
    folder = tmp_path_factory.mktemp("hex")
    make_problem(folder, kind="polygon", extra="\nn_blades = 6\nrotation_deg = 10.0")
    return folder


def test_discrete_choice_is_named_by_its_parameter_path(hexagon, caplog):
    """[[discrete]] path = the parameter path (as [[free]]); the older model-config key
    still works, with one DeprecationWarning naming the path (logged by the commands), and
    builds the same models."""
    from invglare.commands.fit import logged_deprecations
    from invglare.config import fit_tables

    new = load_fit(write_fit(hexagon, tail=f'\n[[discrete]]\npath = "{BLADES}"\nvalues = [5, 6]\n'))
    assert [(d.path, d.key, d.values, d.truth) for d in new.discrete] == [
        (BLADES, "model.shapes.0.n_blades", (5, 6), 6)
    ]
    assert new.candidates() == [{BLADES: 5}, {BLADES: 6}]
    old_tail = '\n[[discrete]]\nkey = "model.shapes.0.n_blades"\nvalues = [5, 6]\n'
    fit_tables._WARNED.discard("model.shapes.0.n_blades")
    with pytest.warns(DeprecationWarning, match=re.escape(f"path = {BLADES!r}")):
        old = load_fit(write_fit(hexagon, tail=old_tail, name="old.toml"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # once per spelling: the second read is quiet
        load_fit(write_fit(hexagon, tail=old_tail, name="old.toml"))
    assert old.discrete == new.discrete
    fit_tables._WARNED.discard("model.shapes.0.n_blades")
    with caplog.at_level(logging.WARNING, logger="invglare"), logged_deprecations(Path("x.toml")):
        load_fit(write_fit(hexagon, tail=old_tail, name="old.toml"))
    assert (
        "x.toml: discrete[0]: key = 'model.shapes.0.n_blades' (a model-config key) is "
        "deprecated; name the choice by its parameter path, as [[free]] does: path = "
        f"{BLADES!r}" in caplog.text
    )
    # A stored choice (params.json) in either spelling rebuilds the same model.
    five = new.forward_for(new.choice({BLADES: 5}))
    assert five.model.aperture.shapes[0].n_blades == 5
    assert old.choice({"model.shapes.0.n_blades": 5}) == {BLADES: 5}
    assert eqx.tree_equal(old.forward_for({"model.shapes.0.n_blades": 5}), five)
    with pytest.raises(ConfigError, match="not one of this fit's"):
        new.choice({"model.shapes.0.rotation_deg": 5})


@pytest.mark.slow
def test_discrete_blade_count_picks_the_truth(hexagon, tmp_path):
    """A hexagonal stop; [[discrete]] tries 5 and 6 blades and keeps the lower loss (6)."""
    tail = f'\n[[discrete]]\npath = "{BLADES}"\nvalues = [5, 6]\n'
    config = write_fit(hexagon, tail=tail, name="blades.toml")
    out = tmp_path / "hex_report"
    result = invoke("fit", config, "--out-dir", out, "--no-progress")
    assert result.exit_code == 0, result.output
    params = json.loads((out / "params.json").read_text())
    blades = params["discrete"][BLADES]
    assert blades["value"] == 6 and blades["truth"] == 6
    losses = {c["value"]: c["loss"] for c in blades["candidates"]}
    assert losses[6] < losses[5]
    assert "## Discrete choices" in (out / "report.md").read_text()


# --------------------------------------------------------------------------------------
# bad input: each a one-line error through the CLI, nothing written


def _nan_exr(path: Path, data: np.ndarray) -> None:
    # write_exr refuses NaN, as it should; a camera pipeline may still produce one.
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"Y": data.astype(np.float32)}) as exr:
        exr.write(str(path))


def _bad_target(folder: Path, kind: str) -> str:
    good = np.asarray(read_exr(folder / "photo.exr").data, dtype=np.float64)
    if kind == "png8":
        grey = np.clip(good / good.max(), 0, 1) ** (1 / 2.2)
        write_png(folder / "bad.png", np.stack([grey] * 3, axis=-1))  # 8-bit sRGB, tone-mapped
        return "bad.png"
    if kind == "tonemapped":
        data = np.round(np.clip(good / good.max(), 0, 1) ** (1 / 2.2) * 255) / 255
    elif kind == "zeros":
        data = np.zeros_like(good)
    elif kind == "saturated":
        data = np.full_like(good, 30000.0)
    elif kind == "nan":
        data = good.copy()
        data[10, 20] = np.nan
        _nan_exr(folder / "bad.exr", data)
        return "bad.exr"
    write_exr(folder / "bad.exr", data, pixel_scale_deg=0.0035)
    return "bad.exr"


@pytest.mark.parametrize(
    ("kind", "match"),
    [
        ("png8", "8-bit PNG image, display-encoded"),
        ("tonemapped", "tone-mapped"),
        ("zeros", "all zeros"),
        ("saturated", "saturation level"),
        ("nan", "non-finite"),
    ],
)
def test_bad_photos_are_refused_with_the_reason(disk, tmp_path, kind, match):
    folder = tmp_path / kind
    shutil.copytree(disk, folder, ignore=shutil.ignore_patterns("*report*"))
    config = write_fit(folder, target=_bad_target(folder, kind))
    with pytest.raises(InputDataError, match=match):
        load_fit(config)
    result = invoke("fit", config, "--out-dir", folder / "out")
    assert result.exit_code == 2, result.output
    errors = [line for line in result.output.splitlines() if line.startswith("invglare: error:")]
    assert len(errors) == 1 and match in errors[0]
    assert not (folder / "out").exists()


@pytest.mark.parametrize(
    ("edit", "error", "match"),
    [
        (dict(target="missing.exr"), InputDataError, "does not exist"),
        (
            dict(free=FREE_DIAMETER.replace("diameter_mm", "diametre_mm")),
            ConfigError,
            "Did you mean 'model.aperture.shapes[0].diameter_mm'",
        ),
        (dict(free=FREE_DIAMETER + "init = 6.0\n"), ConfigError, "not strictly inside"),
        (dict(free=FREE_DIAMETER + "int = 3.0\n"), ConfigError, "unknown key 'int'"),
        (dict(solver_extra="solvr = 'lm'\n"), ConfigError, "unknown key 'solvr'"),
        (dict(tail="\n[views]\npixles = 1.0\n"), ConfigError, "valid views: pixels"),
        (dict(tail="\n[fitt]\nname = 'x'\n"), ConfigError, "unknown section [fitt]"),
        (dict(solver_extra="coarse_to_fine = [2]\n"), ConfigError, "ending with 1"),
        (
            dict(tail='\n[[discrete]]\nkey = "model.shapes.0.diameter_mm"\nvalues = [3]\n'),
            ConfigError,
            "not an integer",
        ),
        (
            dict(tail=f'\n[[discrete]]\npath = "{DIAMETER}"\nvalues = [3]\n'),
            ConfigError,
            "is a fitted value (a float leaf): fit it as a [[free]] parameter",
        ),
        (
            dict(tail='\n[[discrete]]\nkey = "model.shapes.0.n_blade"\nvalues = [3]\n'),
            ConfigError,
            "has no key 'model.shapes.0.n_blade' (stopped at 'n_blade')",
        ),
    ],
)
def test_bad_configs_are_one_line_errors(disk, tmp_path, edit, error, match):
    folder = tmp_path / "cfg"
    shutil.copytree(disk, folder, ignore=shutil.ignore_patterns("*report*"))
    config = write_fit(folder, **edit)
    with pytest.raises(error, match=None) as err:
        load_fit(config)
    assert match in str(err.value)
    result = invoke("fit", config, "--out-dir", folder / "out")
    assert result.exit_code == 2 and match in result.output
    assert not (folder / "out").exists()


# --------------------------------------------------------------------------------------
# Ctrl-C


def _interrupt(*args, **kwargs):
    raise KeyboardInterrupt


def test_ctrl_c_during_the_fit_leaves_no_report(disk, monkeypatch):
    import invglare.fit.stages

    monkeypatch.setattr(invglare.fit.stages, "fit", _interrupt)
    out = disk / "interrupted"
    result = invoke("fit", write_fit(disk), "--out-dir", out, "--no-progress")
    assert result.exit_code == 130 and "interrupted" in result.output
    assert not out.exists()
    assert not [p for p in disk.iterdir() if p.name.startswith(".interrupted")]


def test_ctrl_c_while_writing_keeps_the_previous_report(disk, disk_report, monkeypatch):
    """Interrupted half-way through the figures: the old report is intact, no temp folder."""
    import invglare.fit.report as report

    out, _, _ = disk_report
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    def half_then_interrupt(folder, *args, **kwargs):
        (folder / "images.png").write_bytes(b"half a png")
        raise KeyboardInterrupt

    monkeypatch.setattr(report, "_figures", half_then_interrupt)
    # The same config as the report's: its solves are compiled already.
    result = invoke("fit", write_fit(disk, tail=STAGE), "--out-dir", out, "--no-progress")
    assert result.exit_code == 130
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert not [p for p in out.parent.iterdir() if p.name.startswith(f".{out.name}.")]


# --------------------------------------------------------------------------------------
# recovery on the bundled photos (the acceptance tolerances)

#: path -> (tolerance, relative?) for the parameters of interest of each bundled fit.
TOLERANCES = {
    "eye_daylight": {
        "model.aperture.pupil.diameter_mm": (0.02, True),  # pupil within 2 %
        "model.aperture.upper_lashes.count": (1.0, False),  # lash count within 1
        "model.aperture.upper_lashes.mean_angle_deg": (1.0, False),  # lash angle within 1 deg
    },
    "eye_night": {
        "model.aperture.pupil.diameter_mm": (0.02, True),
        "model.aperture.gratings.spacing_mm": (0.03, True),  # grating spacing within 3 %
        "model.aperture.particles[1].count": (0.10, True),  # particle count within 10 %
    },
    "camera_cross_screen": {
        "model.aperture.diaphragm.rotation_deg": (0.5, False),  # rotation within 0.5 deg
    },
    "false_lashes_camera": {
        "model.aperture.pupil.diameter_mm": (0.02, True),
        "model.aperture.upper_lashes.count": (1.0, False),
        "model.aperture.upper_lashes.mean_angle_deg": (1.0, False),
    },
    # Each ghost's intensity within 5 % and position within 0.5 px: _check_recovery.
    "veiling_cooke": {
        "model.light_angle_deg[0]": (0.04, False),  # 0.5 px of 0.08 deg
        "model.light_angle_deg[1]": (0.04, False),
        "model.ghosts.lens.sensor_reflectance": (0.05, True),
    },
    # The holographic eye's focus (0.625 D: 1.6 m) and pupil from a defocused light.
    "holographic_defocus": {
        "model.aperture.pupil.diameter_mm": (0.02, True),
        "model.accommodation_d": (0.01, False),  # within 0.01 D: 1.6 m to 3 %
    },
}


def _check_recovery(name: str, params: dict) -> None:
    for path, (tol, relative) in TOLERANCES[name].items():
        entry = params["parameters"][path]
        limit = tol * abs(entry["truth"]) if relative else tol
        assert abs(entry["value"] - entry["truth"]) <= limit, (path, entry)
    for key, entry in params.get("discrete", {}).items():
        assert entry["value"] == entry["truth"], key  # blade count exact
    if "ghosts" in params:
        ghosts = params["ghosts"]
        assert ghosts["max_position_error_px"] <= 0.5 and ghosts["max_intensity_rel_error"] <= 0.05
        assert len(ghosts["position_error_px"]) == ghosts["n_ghosts"] > 0
    assert math.isfinite(params["loss"])


@pytest.mark.parametrize("name", list(TOLERANCES))
def test_committed_reports_meet_the_tolerances(name):
    """The committed reports/NAME/ of each bundled fit: complete, and within tolerance."""
    folder = ROOT / "reports" / name
    for file in ("report.md", "params.json", "images.png", "profiles.png", "loss.png"):
        assert (folder / file).is_file(), file
    params = json.loads((folder / "params.json").read_text())
    assert params["fit"]["config"] == f"fits/{name}.toml"
    truth = json.loads((ROOT / "data_synthetic" / f"{name}.truth.json").read_text())
    for path, value in truth["set"].items():
        if path in params["parameters"]:
            assert params["parameters"][path]["truth"] == pytest.approx(value), path
    _check_recovery(name, params)


#: Bundled fits rerun by the suite (about 3 CPU minutes each): the README's main job. The
#: others share its code paths (stages, scans); the camera's blade-count sweep is rerun on
#: a smaller photo by test_discrete_blade_count_picks_the_truth. Their committed reports
#: are checked above, and the golden regression catches a change in the physics they
#: rest on.
RERUN = ("eye_daylight",)


@pytest.mark.slow
@pytest.mark.parametrize("name", RERUN)
def test_bundled_fit_recovers_the_truth(name, tmp_path):
    """The bundled config from its 3+ starts across the bounds, checked against the truth."""
    bounds = {f["path"]: (f["lower"], f["upper"]) for f in load_toml(FITS / f"{name}.toml")["free"]}
    out = tmp_path / name
    result = invoke("fit", FITS / f"{name}.toml", "--out-dir", out, "--no-progress")
    assert result.exit_code == 0, result.output
    params = json.loads((out / "params.json").read_text())
    _check_recovery(name, params)
    for path in TOLERANCES[name]:
        # The starts came from points spread across the bounds, one per stratum (a Latin
        # hypercube): the starts themselves, or the scan that picked them.
        lower, upper = bounds[path]
        scan = params["stages"][0].get("scan")
        points = scan["points"] if scan else params["starts"]
        n = len(points)
        assert sorted(stratum(s[path], lower, upper, n) for s in points) == list(range(n))
    assert len(params["starts"]) >= 3


def test_refit_replaces_the_report_but_keeps_the_posterior(tmp_path):
    """A new report replaces the old as a whole, except the sampled chain of `sample`."""
    from invglare.fit.report import atomic_directory

    target = tmp_path / "eye"
    (target / "posterior").mkdir(parents=True)
    (target / "posterior" / "chain.h5").write_text("chain")
    (target / "stale.png").write_text("old figure")
    with atomic_directory(target, keep=("posterior",)) as tmp:
        (tmp / "report.md").write_text("new")
    assert (target / "posterior" / "chain.h5").read_text() == "chain"
    assert (target / "report.md").read_text() == "new"
    assert not (target / "stale.png").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["eye"]  # no hidden leftovers
