"""``invglare render`` of the holographic eye: the scene handed to the model as a whole."""

import tomllib
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from invglare.cli import app
from invglare.config.model import build_model
from invglare.files.exr import read_exr, write_exr

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "holographic_eye.toml"
runner = CliRunner()


def _small_config(tmp_path: Path) -> Path:
    """The bundled example on a 64-pixel grid (the test's size), as a file."""
    text = EXAMPLE.read_text()
    assert "[output]" not in text or "npix" in text
    path = tmp_path / "holo.toml"
    config = tomllib.loads(text)
    config.setdefault("output", {})["npix"] = 64
    lines = []
    for section, table in config.items():
        lines += _toml_table(section, table)
    path.write_text("\n".join(lines) + "\n")
    return path


def _toml_table(name: str, table: dict) -> list[str]:
    out, subs = [f"[{name}]"], []
    for key, value in table.items():
        if isinstance(value, dict):
            subs += _toml_table(f"{name}.{key}", value)
        elif isinstance(value, str):
            out.append(f'{key} = "{value}"')
        elif isinstance(value, bool):
            out.append(f"{key} = {'true' if value else 'false'}")
        elif isinstance(value, float) and value == float("inf"):
            out.append(f"{key} = inf")
        else:
            out.append(f"{key} = {value!r}")
    return out + subs


@pytest.mark.slow
def test_render_command_renders_the_scene_through_the_holographic_eye(tmp_path):
    config = _small_config(tmp_path)
    frame = np.zeros((48, 48, 3), np.float32)
    frame[24, 24] = 100.0
    scene = tmp_path / "scene.exr"
    write_exr(scene, frame, pixel_scale_deg=0.01)
    out = tmp_path / "out.exr"
    result = runner.invoke(
        app, ["render", str(scene), "--model", str(config), "--iterations", "2", "--out", str(out)]
    )
    assert result.exit_code == 0, result.output + repr(result.exception)
    img = read_exr(out, allow_negative=True)
    # The same call in Python gives the same image: the command adds nothing of its own.
    model = build_model(tomllib.loads(config.read_text()))
    expected = np.asarray(model.render(frame, None, 0, iterations=2))
    assert img.pixel_scale_deg == pytest.approx(float(model.pixel_scale_deg))
    np.testing.assert_allclose(img.data, expected, rtol=1e-5, atol=1e-6 * expected.max())
    # A clear eye keeps the light: most of the source's energy is in the image.
    assert 0.5 * frame.sum() < img.data.sum() <= 1.01 * frame.sum()


def test_iterations_are_refused_for_a_model_that_does_not_render_scenes(tmp_path):
    scene = tmp_path / "scene.exr"
    write_exr(scene, np.ones((16, 16), np.float32), pixel_scale_deg=0.01)
    circle = Path(__file__).resolve().parents[2] / "examples" / "circle.toml"
    result = runner.invoke(
        app,
        ["render", str(scene), "--model", str(circle), "--iterations", "4",
         "--out", str(tmp_path / "o.exr")],
    )  # fmt: skip
    assert result.exit_code == 2
    assert "render whole scenes" in result.output and "AperturePSF" in result.output
