"""``method = "quad"`` from a config through ``invglare psf`` and ``invglare render``, and
its bad options as one-line CLI errors."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from invglare.cli import app
from invglare.files.exr import read_exr

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "heptagon_quad.toml"
runner = CliRunner()


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


def _small(tmp_path, **replace) -> Path:
    """The README's example at a test's size (64 px raster, 48 px output)."""
    text = EXAMPLE.read_text().replace("aperture_npix = 128", "aperture_npix = 64")
    text = text.replace("npix = 256", "npix = 48")
    for old, new in replace.items():
        assert old in text
        text = text.replace(old, new)
    cfg = tmp_path / "quad.toml"
    cfg.write_text(text)
    return cfg


@pytest.mark.slow
def test_psf_and_render_with_the_quad_method(tmp_path):
    cfg = _small(tmp_path)
    out = tmp_path / "psf.exr"
    result = invoke("psf", cfg, "--wavelengths-nm", 550, "--out", out, "--png", tmp_path / "p.png")
    assert result.exit_code == 0, result.output
    img = read_exr(out)
    model = img.config["model"]
    assert model["method"] == "quad" and model["quad"]["cull_below"] == pytest.approx(1e-7)
    assert img.data.shape == (48, 48) and img.pixel_scale_deg == pytest.approx(0.002)
    # Peak at the centre; per unit power through the aperture (the heptagon's closed-form
    # area, 3.6 mm across), the peak of a hard-edged aperture's far field is area / lambda^2
    # per steradian: measured 2.1e-4 high (the 64 px raster's area; the old sum |t|^2
    # normalisation needed 3 %).
    assert np.unravel_index(np.argmax(img.data), img.data.shape) == (24, 24)
    area = 7 / 2 * 1.8**2 * math.sin(2 * math.pi / 7)
    peak = area / (550e-6) ** 2 * math.radians(0.002) ** 2
    assert img.data.max() == pytest.approx(peak, rel=1e-3)
    scene = tmp_path / "street.exr"
    assert invoke("scene", "street_lights_at_night", "--npix", 48, "--out", scene).exit_code == 0
    rendered = tmp_path / "rendered.exr"
    result = invoke("render", scene, "--model", cfg, "--out", rendered)
    assert result.exit_code == 0, result.output
    # Light moved around, not created (the quad PSF's energy in this small field < 1).
    assert 0.8 < read_exr(rendered).data.sum() / read_exr(scene).data.sum() <= 1.0


@pytest.mark.parametrize(
    ("replace", "pattern"),
    [
        ({"cull_below = 1e-7": "cull_below = 2.0"}, "cull_below"),
        ({"symmetry = \"auto\"": "symmetry = \"radial\""}, "symmetry"),
        ({"[model.quad]": "[model.polygon]"}, "model.polygon"),
        ({"diameter_mm = 3.6": "diameter_mm = 0.0"}, "diameter_mm|empty"),
        ({"pixel_scale_deg = 0.002": "pixel_scale_deg = 40.0"}, "represent|aperture"),
    ],
)
def test_bad_quad_configs_are_one_line_errors(tmp_path, replace, pattern):
    cfg = _small(tmp_path, **replace)
    result = invoke("psf", cfg, "--wavelengths-nm", 550, "--out", tmp_path / "x.exr")
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output
    assert re.search(pattern, result.output), result.output
