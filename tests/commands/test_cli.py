"""The `invglare` command: psf end to end, one-line errors, bench reports."""

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from invglare.cli import app
from invglare.files.exr import read_exr

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
runner = CliRunner()


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


def test_help_is_instant_and_does_not_import_jax():
    code = "import sys, invglare.cli; print('jax' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
    assert invoke("--help").exit_code == 0


#: Runs a command in this process and says whether JAX was loaded when it ended.
TYPO_PROBE = """
import sys, time
from invglare.cli import main
sys.argv = ["invglare", *sys.argv[1:]]
t0 = time.perf_counter()
try:
    main()
except SystemExit as e:
    print(e.code, "jax" in sys.modules, time.perf_counter() - t0)
"""


@pytest.mark.parametrize("command", ["fit", "sample", "fit-batch"])
def test_a_misspelt_section_is_named_before_jax_loads(command, tmp_path):
    """A typo in a fit config is reported before JAX is imported (which takes seconds)."""
    config = tmp_path / "fit.toml"
    config.write_text('[target]\nfile = "photo.exr"\n\n[modle]\nconfig = "eye.toml"\n')
    args = [command, str(config)] + (["photo.exr"] if command == "fit-batch" else [])
    out = subprocess.run([sys.executable, "-c", TYPO_PROBE, *args], capture_output=True,
                         text=True, check=True, cwd=tmp_path)  # fmt: skip
    code, jax_loaded, seconds = out.stdout.split()
    assert "unknown section [modle]" in out.stderr, out.stderr
    assert (code, jax_loaded) == ("2", "False"), out.stderr
    assert float(seconds) < 10.0  # a generous bound: what is checked is the import order


#: A model config with a misspelt section, and one whose [model] has no kind.
MODEL_TYPOS = {
    "unknown section [ouput]": '[model]\nkind = "aperture"\n\n[ouput]\nnpix = 64\n',
    "needs the key 'kind'": '[model]\nknid = "aperture"\n',
}


@pytest.mark.parametrize("typo", sorted(MODEL_TYPOS))
@pytest.mark.parametrize("command", ["psf", "render", "export-kernel"])
def test_a_model_config_typo_is_named_before_jax_loads(command, typo, tmp_path):
    """psf, render and export-kernel check a model config's tables before importing JAX."""
    config = tmp_path / "model.toml"
    config.write_text(MODEL_TYPOS[typo])
    args = {
        "psf": ["psf", str(config)],
        "render": ["render", "scene.exr", "--model", str(config), "--out", "out.exr"],
        "export-kernel": ["export-kernel", str(config), "--for", "blender", "--out", "k.exr"],
    }[command]
    out = subprocess.run([sys.executable, "-c", TYPO_PROBE, *args], capture_output=True,
                         text=True, check=True, cwd=tmp_path)  # fmt: skip
    code, jax_loaded, seconds = out.stdout.split()
    assert typo in out.stderr and str(config) in out.stderr, out.stderr
    assert (code, jax_loaded) == ("2", "False"), out.stderr
    assert float(seconds) < 10.0  # a generous bound: what is checked is the import order
    assert not any(tmp_path.glob("*.exr"))  # nothing was written


def test_version_is_the_package_version():
    """`invglare --version` prints the version pyproject.toml declares, without JAX."""
    import tomllib

    declared = tomllib.loads((EXAMPLES.parent / "pyproject.toml").read_text())["project"]
    result = invoke("--version")
    assert result.exit_code == 0 and result.output == f"invglare {declared['version']}\n"


def test_psf_readme_command_writes_airy_exr(tmp_path):
    out = tmp_path / "psf.exr"
    png = tmp_path / "psf.png"
    result = invoke(
        "psf",
        EXAMPLES / "circle.toml",
        "--npix",
        128,
        "--pixel-scale-deg",
        0.0004,
        "--wavelengths-nm",
        550,
        "--out",
        out,
        "--png",
        png,
    )
    assert result.exit_code == 0, result.output
    img = read_exr(out)
    assert img.channels == ("Y",)
    assert img.data.shape == (128, 128)
    assert img.pixel_scale_deg == pytest.approx(0.0004)
    assert img.wavelengths_nm == (550.0,)
    assert img.config["model"]["shapes"][0]["kind"] == "disk"
    assert img.config["model"]["method"] == "mft"
    # Airy: the peak at the centre, first dark ring at 1.22 lambda / D (= 19.2 px here).
    assert np.unravel_index(np.argmax(img.data), img.data.shape) == (64, 64)
    ring_px = 1.21967 * math.degrees(550e-6 / 4.0) / 0.0004
    row = img.data[64, 64:]
    k = int(np.argmin(row[10:30])) + 10
    assert abs(k - ring_px) <= 1.0
    assert png.exists() and png.stat().st_size > 0


def test_psf_spectral_example_writes_rgb(tmp_path):
    out = tmp_path / "hex.exr"
    result = invoke(
        "psf",
        EXAMPLES / "hexagon_spectral.toml",
        "--npix",
        64,
        "--wavelengths-nm",
        "450:650:4",
        "--out",
        out,
    )
    assert result.exit_code == 0, result.output
    # Saturated spectral colours lie outside sRGB: small negative values are expected.
    img = read_exr(out, allow_negative=True)
    assert img.channels == ("R", "G", "B")
    assert img.wavelengths_nm == (450.0, 500.0, 550.0, 600.0)
    assert img.data.min() > -0.01 * img.data.max()


def test_psf_fresnel_example_runs_on_fft_path(tmp_path):
    out = tmp_path / "fresnel.exr"
    result = invoke("psf", EXAMPLES / "pupil_fresnel.toml", "--npix", 128, "--out", out)
    assert result.exit_code == 0, result.output
    img = read_exr(out)
    assert img.config["model"]["method"] == "fft"
    assert img.config["model"]["propagation"] == "fresnel"


@pytest.mark.parametrize("name", ["eye_daylight", "camera_cross_screen"])
@pytest.mark.slow
def test_psf_and_render_take_the_eye_and_camera_configs(tmp_path, name):
    """The Kakimoto models from the CLI: a PSF with its config in the header, then a scene
    convolved with it (light moved around, not created: the frame keeps the light the PSF
    holds, per unit power through the aperture: 0.93 for the eye, 0.82 for the cross-screen
    camera, whose raster's sharp, sub-pixel edges send the rest beyond its angles)."""
    from invglare.config.model import build_model
    from invglare.files.toml import load_toml

    out = tmp_path / f"{name}.exr"
    result = invoke("psf", EXAMPLES / f"{name}.toml", "--npix", 64, "--out", out)
    assert result.exit_code == 0, result.output
    img = read_exr(out)
    kind = name.split("_")[0]
    assert img.config["model"]["kind"] == kind and img.data.shape[:2] == (64, 64)
    assert np.all(np.isfinite(img.data)) and img.data.max() > 0
    scene = tmp_path / "street.exr"
    assert invoke("scene", "street_lights_at_night", "--npix", 64, "--out", scene).exit_code == 0
    rendered = tmp_path / "rendered.exr"
    result = invoke("render", scene, "--model", EXAMPLES / f"{name}.toml", "--out", rendered)
    assert result.exit_code == 0, result.output
    held = float(np.sum(build_model(load_toml(EXAMPLES / f"{name}.toml"), EXAMPLES)()))
    assert 0.75 < held < 1.0
    expected = read_exr(scene).data.sum() * held
    assert read_exr(rendered).data.sum() == pytest.approx(expected, rel=0.05)


def test_psf_refuses_an_aliased_fresnel_phase(tmp_path):
    cfg = tmp_path / "aliased.toml"
    text = (EXAMPLES / "pupil_fresnel.toml").read_text().replace("aperture_npix = 512", "")
    cfg.write_text(text)
    result = invoke("psf", cfg, "--out", tmp_path / "x.exr")
    assert result.exit_code == 2
    assert "Fresnel phase (eq. 3) aliases" in result.output
    assert "aperture_npix >= " in result.output


def test_scene_and_render_commands(tmp_path):
    scene = tmp_path / "street.exr"
    assert invoke("scene", "street_lights_at_night", "--npix", 64, "--out", scene).exit_code == 0
    for mode, out in (("convolve", "a.exr"), ("billboard", "b.png")):
        result = invoke(
            "render",
            scene,
            "--model",
            EXAMPLES / "pupil_with_lashes.toml",
            "--mode",
            mode,
            "--max-bright",
            8,
            "--out",
            tmp_path / out,
        )
        assert result.exit_code == 0, result.output
    original = read_exr(scene).data
    glare = read_exr(tmp_path / "a.exr").data
    # Convolution with a unit-energy PSF moves light around but does not create it.
    assert glare.sum() == pytest.approx(original.sum(), rel=0.02)
    assert glare.max() < original.max()
    bad = invoke("render", scene, "--model", EXAMPLES / "circle.toml", "--out", tmp_path / "x.jpg")
    assert bad.exit_code == 2 and ".exr or .png" in bad.output
    assert invoke("scene", "moon", "--out", tmp_path / "m.exr").exit_code == 2


@pytest.mark.parametrize(
    ("toml", "args", "pattern"),
    [
        (
            '[model]\nkind="aperture"\nfocal_length_mm=17\n[[model.shapes]]\nkind="disk"\ndiameter=4\n',
            [],
            "unknown key 'diameter'",
        ),
        (
            '[model]\nkind="aperture"\nfocal_length_mm=17\n[[model.shapes]]\nkind="disk"\ndiameter_mm=4\n'
            "[outptu]\nnpix=64\n",
            [],
            r"unknown section \[outptu\]",
        ),
        (
            '[model]\nkind="aperture"\nfocal_length_mm="17"\n[[model.shapes]]\nkind="disk"\n'
            "diameter_mm=4\n",
            [],
            "model.focal_length_mm must be a number",
        ),
        (
            '[model]\nkind="aperture"\nfocal_length_mm=17\n[[model.shapes]]\nkind="disk"\n'
            "diameter_mm=-4\n",
            [],
            "diameter_mm",
        ),
        (
            '[model]\nkind="aperture"\nfocal_length_mm=17\n[[model.shapes]]\nkind="disk"\n'
            "diameter_mm=4\n",
            ["--wavelengths-nm", "5.5e-7"],
            "metres",
        ),
        ('[model]\nkind="lens"\n', [], "model.kind = 'lens' is unknown"),
        ("[model\n", [], "not valid TOML"),
    ],
)
def test_psf_bad_config_is_one_line_error(tmp_path, toml, args, pattern):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(toml)
    out = tmp_path / "x.exr"
    result = invoke("psf", cfg, "--out", out, *args)
    assert result.exit_code == 2
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("invglare: error:"), result.output
    import re

    assert re.search(pattern, lines[0]), lines[0]
    assert not out.exists()


def test_psf_missing_config_file(tmp_path):
    result = invoke("psf", tmp_path / "nope.toml")
    assert result.exit_code == 2
    assert "does not exist" in result.output


def test_bench_writes_records_with_ratios(tmp_path):
    result = invoke("bench", "psf_mono", "--sizes", "32", "--repeats", "3", "--out-dir", tmp_path)
    assert result.exit_code == 0, result.output
    records = json.loads((tmp_path / "bench.json").read_text())["records"]
    names = {r["case"] for r in records}
    assert {"fft_floor_scipy", "psf_mono", "psf_mono_grad"} <= names
    for r in records:
        assert {"case", "size", "median_ms", "floor_ms", "ratio"} <= r.keys()
        assert r["median_ms"] > 0 and r["ratio"] > 0
    grad = next(r for r in records if r["case"] == "psf_mono_grad")
    assert grad["vs_forward"] > 0
    assert "| psf_mono | 32 |" in (tmp_path / "bench.md").read_text()


def test_bench_unknown_case_is_an_error(tmp_path):
    result = invoke("bench", "no_such_case", "--sizes", "32", "--out-dir", tmp_path)
    assert result.exit_code == 2
    assert "no benchmark case matches" in result.output
