"""``invglare export-kernel`` end to end: the exported EXR, loaded as Blender and Unreal load
it and convolved the way each does (the re-implementations of
``tests/render/test_kernels.py``), gives the frame ``invglare render`` writes for the same
model and scene; bad requests are refused before the PSF is computed.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
from typer.testing import CliRunner

from invglare.cli import app
from invglare.files.exr import read_exr, write_exr

ROOT = Path(__file__).resolve().parents[2]
runner = CliRunner()

# A 6-blade camera stop in three colours, small enough to compute in a second or two.
HEXAGON = """
[model]
kind = "aperture"
focal_length_mm = 50.0
aperture_npix = 96

[[model.shapes]]
kind = "polygon"
n_blades = 6
diameter_mm = 6.25
rotation_deg = 15.0

[output]
npix = 64
pixel_scale_deg = 0.0025

[spectrum]
wavelengths_nm = [450.0, 550.0, 650.0]
"""
SCALE = 0.005  # the scene's deg/px: two model pixels per scene pixel (the resampled path)
RTOL = 1e-5  # of the frame's largest value, as in tests/render/test_kernels.py


def _tools():
    """The renderers' convolutions, re-implemented in tests/render/test_kernels.py."""
    spec = importlib.util.spec_from_file_location(
        "kernel_tools", ROOT / "tests" / "render" / "test_kernels.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _run(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """The model config, a 40 x 48 RGB scene at SCALE and `invglare render`'s frame of it."""
    base = tmp_path_factory.mktemp("export_kernel")
    config = base / "hexagon.toml"
    config.write_text(HEXAGON)
    rng = np.random.default_rng(5)
    scene = 0.02 * rng.random((40, 48, 3))
    scene[12, 9] = (2e3, 1.5e3, 1e3)
    scene[30, 40] = (10.0, 40.0, 90.0)
    write_exr(base / "scene.exr", scene.astype(np.float32), pixel_scale_deg=SCALE)
    result = _run("render", base / "scene.exr", "--model", config, "--out", base / "render.exr")
    assert result.exit_code == 0, result.output
    render = read_exr(base / "render.exr").data.astype(np.float64)
    return base, config, read_exr(base / "scene.exr").data, render


def _load_as_the_tools_do(path: Path) -> tuple[np.ndarray, OpenEXR.File]:
    with OpenEXR.File(str(path), separate_channels=True) as exr:
        channels = exr.channels()
        header = dict(exr.header())
        assert sorted(channels) == ["B", "G", "R"]
        assert {ch.pixels.dtype for ch in channels.values()} == {np.dtype(np.float32)}
        return np.stack([channels[c].pixels for c in "RGB"], axis=-1), header


def test_blender_kernel_round_trip_through_invglare_render(setup, caplog):
    caplog.set_level("INFO", logger="invglare")
    base, config, scene, render = setup
    out = base / "blender.exr"
    result = _run(
        "export-kernel", config, "--for", "blender", "--out", out, "--pixel-scale-deg", SCALE
    )
    assert result.exit_code == 0, result.output
    kernel, header = _load_as_the_tools_do(out)
    n = kernel.shape[0]
    assert kernel.shape == (n, n, 3) and n % 2 == 1
    assert header["pixelScaleDeg"] == pytest.approx(SCALE)
    assert header["kernelTarget"] == "blender" and header["kernelPointReflected"] == 1
    energy = np.asarray(header["kernelChannelEnergy"], np.float64)
    np.testing.assert_allclose(energy, kernel.sum(axis=(0, 1)), rtol=1e-5)
    tools = _tools()
    scale = RTOL * render.max()
    # Convolve node, Normalize Kernel off: exactly `invglare render`.
    got = tools.blender_convolve(scene, kernel, normalize=False)
    assert np.max(np.abs(got - render)) <= scale
    # Glare node (always normalised), Tint = the printed energies, Glare output.
    glare, _ = tools.blender_glare_output(scene, kernel, 0.0, 1.0, energy)
    assert np.max(np.abs(glare - render)) <= scale
    # The tint the normalisation removes is a real one for this three-colour PSF.
    assert energy.max() - energy.min() > 1e-3
    assert "becomes neutral" in caplog.text and "Normalize Kernel is off" in caplog.text
    assert "rotated by 180 deg" in caplog.text


def test_unreal_kernel_round_trip_through_invglare_render(setup, caplog):
    caplog.set_level("INFO", logger="invglare")
    base, config, scene, render = setup
    out = base / "unreal.exr"
    viewport = "48x40"
    result = _run(
        "export-kernel", config, "--for", "unreal", "--out", out,
        "--pixel-scale-deg", SCALE, "--viewport", viewport,
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    texture, header = _load_as_the_tools_do(out)
    n = texture.shape[0]
    assert n % 2 == 1 and n <= 39  # odd, and no larger than the screen's minor axis
    c = n // 2
    lum = texture @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    assert np.unravel_index(lum.argmax(), lum.shape) == (c, c)  # peak at UV (0.5, 0.5)
    size = header["unrealConvolutionScale"]
    assert size == pytest.approx(n / 40)
    assert f"Convolution Scale = {n}/40" in caplog.text
    fraction = np.asarray(header["kernelCentreFraction"])
    np.testing.assert_allclose(fraction, texture[c, c] / texture.sum(axis=(0, 1)), rtol=1e-5)
    bloom = _tools().unreal_bloom(scene, texture, size, (48, 40))
    energy = texture.sum(axis=(0, 1)).astype(np.float64)
    assert np.max(np.abs(bloom * energy - render)) <= RTOL * render.max()


def test_a_mono_model_gives_an_untinted_kernel(tmp_path, caplog):
    caplog.set_level("INFO", logger="invglare")
    config = tmp_path / "disk.toml"
    config.write_text(
        '[model]\nkind = "aperture"\nfocal_length_mm = 17.0\naperture_npix = 32\n'
        '[[model.shapes]]\nkind = "disk"\ndiameter_mm = 4.0\n[output]\nnpix = 48\n'
    )
    out = tmp_path / "k.exr"
    result = _run("export-kernel", config, "--for", "blender", "--out", out, "--npix", 31)
    assert result.exit_code == 0, result.output
    kernel, _ = _load_as_the_tools_do(out)
    assert kernel.shape == (31, 31, 3)
    np.testing.assert_array_equal(kernel[..., 0], kernel[..., 1])
    assert "the same energy to within 0.1 %" in caplog.text


@pytest.fixture
def no_psf(monkeypatch):
    """Fail the test if the PSF is computed: the refusals must come before that work."""
    import invglare.commands.render as render

    def refuse(*args, **kwargs):
        raise AssertionError("the PSF was computed before the request was refused")

    monkeypatch.setattr(render, "psf_at_scale", refuse)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--for", "nuke"], "unknown kernel target 'nuke'; choose one of blender, unreal"),
        (["--for", "blender", "--npix", "64"], "kernel size must be odd, got 64"),
        (["--for", "unreal", "--viewport", "1920by1080"], "--viewport must be WIDTHxHEIGHT"),
        (["--for", "unreal", "--fov-deg", "40"], "--fov-deg needs --viewport"),
        (["--for", "blender", "--out", "k.png"], "--out 'k.png' has extension '.png'"),
    ],
)
def test_bad_requests_are_one_line_errors(setup, no_psf, args, message):
    _, config, _, _ = setup
    result = _run("export-kernel", config, *args)
    assert result.exit_code == 2
    assert message in result.output
    assert "Traceback" not in result.output


def test_a_model_that_is_not_shift_invariant_is_refused(no_psf, tmp_path):
    config = ROOT / "examples" / "veiling_ghosts.toml"
    result = _run("export-kernel", config, "--for", "unreal", "--out", tmp_path / "k.exr")
    assert result.exit_code == 2
    assert "depends on the light's direction" in result.output
    assert "--mode billboard" in result.output
    assert not (tmp_path / "k.exr").exists()
