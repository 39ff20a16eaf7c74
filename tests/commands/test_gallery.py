"""`invglare gallery`: one PNG row per model, a markdown page that shows them all."""

import re
import struct
from pathlib import Path

import pytest
from typer.testing import CliRunner

from invglare.cli import app

runner = CliRunner()

EYE = """\
# A tiny eye: 2 mm pupil and a few lashes.
[model]
kind = "eye"
aperture_npix = 48
window_mm = 3.2

[model.eye]
seed = 1

[model.eye.pupil]
diameter_mm = 2.0

[model.eye.lids]
upper_opening_mm = 0.8
lower_opening_mm = 1.0

[model.eye.lashes_upper]
count = 4
n_max = 4
thickness_mm = 0.1
length_mm = 2.0

[output]
npix = 64
pixel_scale_deg = 0.006

[spectrum]
wavelengths_nm = 550
"""

CAMERA = """\
# A tiny camera: a 6-blade diaphragm.
[model]
kind = "camera"
aperture_npix = 48
window_mm = 8.4

[model.camera.diaphragm]
n_blades = 6
f_number = 8.0
focal_length_mm = 50.0

[output]
npix = 64
pixel_scale_deg = 0.002

[spectrum]
wavelengths_nm = 550
"""


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


def png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", f"{path} is not a PNG"
    assert data[12:16] == b"IHDR" and data[-8:-4] == b"IEND"
    return struct.unpack(">II", data[16:24])


@pytest.mark.slow
def test_gallery_writes_a_page_with_one_png_row_per_model(tmp_path):
    eye, camera = tmp_path / "tiny_eye.toml", tmp_path / "tiny_camera.toml"
    eye.write_text(EYE)
    camera.write_text(CAMERA)
    out = tmp_path / "reports"
    result = invoke(
        "gallery", eye, camera, "--out-dir", out, "--npix", 64, "--wavelengths-nm", "450,550,650"
    )
    assert result.exit_code == 0, result.output
    md = (out / "gallery.md").read_text()
    linked = re.findall(r"\]\((gallery/[^)]+\.png)\)", md)
    pngs = sorted(p.relative_to(out).as_posix() for p in (out / "gallery").iterdir())
    assert sorted(linked) == pngs == ["gallery/tiny_camera.png", "gallery/tiny_eye.png"]
    assert "A tiny eye: 2 mm pupil and a few lashes." in md
    for name in pngs:
        width, height = png_size(out / name)
        assert 600 <= width <= 3000 and 200 <= height <= 1200 and width > 2 * height
        assert (out / name).stat().st_size > 10_000  # three panels, not an empty figure
    # A monochrome run (the configs' own 550 nm) replaces the folder as a whole.
    result = invoke(
        "gallery",
        camera,
        "--out-dir",
        out,
        "--npix",
        64,
        "--wavelengths-nm",
        "config",
        "--scene-scale",
        "scene",
    )
    assert result.exit_code == 0, result.output
    assert [p.name for p in (out / "gallery").iterdir()] == ["tiny_camera.png"]
    png_size(out / "gallery" / "tiny_camera.png")
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary left


def test_gallery_reports_a_bad_model_path_in_one_line(tmp_path):
    result = invoke("gallery", tmp_path / "missing.toml", "--out-dir", tmp_path / "reports")
    assert result.exit_code == 2
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and "missing.toml" in lines[0] and "does not exist" in lines[0]
    assert not (tmp_path / "reports").exists()
