"""Kakimoto et al.'s compositing (issue 27, item 8): sigmoid-mapped billboards on the LDR
picture, scaled by each pixel, black kept black."""

import math

import jax.numpy as jnp
import numpy as np
import pytest
from typer.testing import CliRunner

from invglare.errors import InputDataError
from invglare.files.exr import write_exr
from invglare.render import bright_pixel_list, kakimoto_sigmoid, tonemap
from invglare.render.billboard import replace_with_billboards
from invglare.render.composite import kakimoto_billboard_texture, kakimoto_composite


def airy_like_psf(n: int = 33) -> np.ndarray:
    """A bright spot with faint rings, unit sum, centre at n // 2."""
    r = np.hypot(*np.mgrid[:n, :n] - n // 2) + 1e-9
    psf = (np.sin(1.3 * r) / r) ** 2 * np.exp(-r / 9.0)
    psf[n // 2, n // 2] = 50.0
    return psf / psf.sum()


def scene_with_lights(values, positions, shape=(64, 64)):
    scene = np.zeros(shape)
    for v, (r, c) in zip(values, positions, strict=True):
        scene[r, c] = v
    return scene


def test_kakimoto_compositing_keeps_black_at_black():
    """Issue 27 (8): a black scene stays black outside the glare; the sigmoid applied to the
    whole HDR frame (the billboard mode's kakimoto tone map) lifts it to 32 / 255."""
    psf = airy_like_psf()
    scene = scene_with_lights([1e4], [(32, 32)])
    bright = bright_pixel_list(scene, 100.0, 4)
    ldr = tonemap(scene, "reinhard")
    out = np.asarray(kakimoto_composite(ldr, bright, psf, 1.0))
    far = np.max(np.abs(np.mgrid[:64, :64] - 32), axis=0) > 16  # beyond the 33 px billboard
    assert np.all(out[far] == 0.0)
    texture = np.asarray(kakimoto_billboard_texture(np.pad(psf, 4), 1.0))
    assert texture[:4].max() == 0.0 and texture.max() == pytest.approx(1.0)  # no glare: 0
    old = np.asarray(tonemap(np.asarray(replace_with_billboards(scene, bright, psf)), "kakimoto"))
    floor = float(kakimoto_sigmoid(0.0)) / 255.0
    assert old[far].min() == pytest.approx(floor) and floor == pytest.approx(32 / 255)


def test_billboards_scale_with_their_pixel_and_add_after_tone_mapping():
    """A light of half the value gets half the billboard; overlapping lights add their
    tone-mapped billboards (no compression of their sum)."""
    psf = airy_like_psf()
    ldr = jnp.zeros((80, 80))
    a = scene_with_lights([1e4, 5e3], [(18, 18), (60, 60)], (80, 80))
    out = np.asarray(kakimoto_composite(ldr, bright_pixel_list(a, 10.0, 4), psf, 1.0, gain=0.5))
    first, second = out[2:35, 2:35], out[44:77, 44:77]
    assert first.max() < 1.0  # no clipping
    np.testing.assert_allclose(second, 0.5 * first, rtol=1e-5, atol=1e-7)
    both = scene_with_lights([1e4, 1e4], [(30, 30), (30, 36)], (80, 80))
    alone = [scene_with_lights([1e4], [p], (80, 80)) for p in ((30, 30), (30, 36))]

    def composite(scene):
        bright = bright_pixel_list(scene, 10.0, 4)
        return np.asarray(kakimoto_composite(ldr, bright, psf, 1.0, gain=0.2))

    np.testing.assert_allclose(
        composite(both), composite(alone[0]) + composite(alone[1]), atol=1e-6
    )
    with pytest.raises(InputDataError, match="no bright pixel"):
        kakimoto_composite(ldr, bright_pixel_list(np.zeros((64, 64)), 10.0, 4), psf, 1.0)


def test_render_command_kakimoto_mode(tmp_path):
    """`invglare render --mode kakimoto` on a night scene: the dark sky stays black."""
    from invglare.cli import app

    scene = np.full((48, 48, 3), 0.0, np.float32)
    scene[24, 24] = [2e4, 1.8e4, 1.5e4]
    scene[30:, :] = 0.5  # a dim street
    write_exr(tmp_path / "scene.exr", scene, pixel_scale_deg=0.05)
    model = tmp_path / "eye.toml"
    model.write_text(
        '[model]\nkind = "eye"\naperture_npix = 64\n[model.eye]\n[model.eye.pupil]\n'
        "diameter_mm = 3.0\n[output]\nnpix = 64\npixel_scale_deg = 0.008\n"
        "[spectrum]\nwavelengths_nm = [680.0, 530.0, 460.0]\n"
    )
    out = tmp_path / "out.png"
    args = ["render", str(tmp_path / "scene.exr"), "--model", str(model), "--mode", "kakimoto"]
    result = CliRunner().invoke(app, [*args, "--out", str(out)])
    assert result.exit_code == 0, result.output
    import imageio.v3 as iio

    png = np.asarray(iio.imread(out), np.float64) / 255.0
    assert png.shape[:2] == (48, 48)
    assert png[:10, :10].max() == 0.0  # black sky, far from the light
    assert png[24, 24].min() > 0.9 and png[40, 5].max() > 0.0  # the light, the street
    bad = CliRunner().invoke(app, [*args, "--tonemap", "kakimoto", "--out", str(out)])
    assert bad.exit_code == 2 and "sigmoid" in bad.output
    assert math.isfinite(png.sum())
