"""Position-dependent glare rendered onto a frame: each light the PSF of its own direction."""

import functools
import tomllib
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from typer.testing import CliRunner

from invglare.cli import app
from invglare.config.model import build_model
from invglare.errors import InputDataError, PhysicsRangeError
from invglare.files.exr import read_exr, write_exr
from invglare.files.toml import load_toml
from invglare.render import (
    BrightPixels,
    bright_pixel_list,
    light_angles_deg,
    position_psf_bank,
    render_position_glare,
    replace_with_billboards,
    resample_psf,
)
from invglare.render.position_glare import psf_npix_at_scale

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
SCALE = 0.012  # deg per frame pixel: 4 model pixels of 0.003 deg


def _eye_toml(masking: str) -> str:
    """The daylight eye, lighter: 64 px, no cornea cells, 12 lashes (faster to compile)."""
    text = (EXAMPLES / "eye_daylight.toml").read_text()
    text = text[: text.index("[[model.eye.particles]]")] + text[text.index("[output]") :]
    for old, new in (
        ('masking = "fixed"', f'masking = "{masking}"\nmax_light_angle_deg = 1.0'),
        ("aperture_npix = 128", "aperture_npix = 64"),
        ("npix = 256", "npix = 64"),
        ("count = 40\nn_max = 48", "count = 12\nn_max = 12"),
    ):
        assert old in text
        text = text.replace(old, new)
    return text


@functools.cache
def _eye(masking: str):
    return build_model(tomllib.loads(_eye_toml(masking)))


def _frame() -> np.ndarray:
    """A dark 41 x 49 frame with three lights away from the centre (row 20, col 24)."""
    frame = np.full((41, 49), 0.01, np.float32)
    for (row, col), value in {(5, 8): 900.0, (30, 40): 500.0, (20, 24): 300.0}.items():
        frame[row, col] = value
    return frame


def test_light_angles_follow_the_sampling_convention():
    bright = BrightPixels(
        rows=jnp.array([20, 5, 30]),
        cols=jnp.array([24, 8, 40]),
        values=jnp.ones(3),
        valid=jnp.ones(3, bool),
        n_above=jnp.array(3),
    )
    angles = np.asarray(light_angles_deg(bright, (41, 49), SCALE))
    # x grows with the column, y with the row, from the centre pixel (H // 2, W // 2).
    np.testing.assert_allclose(
        angles, [[0, 0], [-16 * SCALE, -15 * SCALE], [16 * SCALE, 10 * SCALE]]
    )


@pytest.mark.slow
def test_each_light_gets_the_psf_of_its_own_direction():
    """The bank equals one model call per light, resampled (rel 1e-5); the lashes make
    the PSFs of different lights differ, and the render is the billboards of that bank."""
    model = _eye("position")
    frame = _frame()
    bright = bright_pixel_list(jnp.asarray(frame), 100.0, 8)
    n = int(bright.n_above)
    assert n == 3
    npix = psf_npix_at_scale(64, 0.003, SCALE, 99)
    assert npix == 17
    angles = light_angles_deg(bright, frame.shape, SCALE)[:n]
    bank = np.asarray(position_psf_bank(model, angles, SCALE, npix, batch_size=2, progress=False))
    call = eqx.filter_jit(lambda m, a: m(a))
    for k in range(n):
        psf = call(model, angles[k])
        one = resample_psf(psf, 0.003, SCALE, npix)
        np.testing.assert_allclose(bank[k], one, rtol=1e-5, atol=1e-6 * float(one.max()))
        # Resampling to the frame's coarser pixels keeps the PSF's energy.
        assert bank[k].sum() == pytest.approx(float(psf.sum()), rel=1e-5)
    with pytest.raises(PhysicsRangeError, match="pixel_scale_deg"):
        position_psf_bank(model, angles, 0.0, npix)
    with pytest.raises(InputDataError, match=r"\(K, 2\)"):
        position_psf_bank(model, angles[:, 0], SCALE, npix)
    # Lights 0.3 deg apart see the lashes shifted by 8 mm * tan(0.3 deg) = 0.04 mm.
    assert np.abs(bank[0] - bank[1]).max() > 1e-3 * bank[0].max()

    out = np.asarray(render_position_glare(model, frame, bright, SCALE, 99, progress=False))
    listed = BrightPixels(*(jnp.asarray(f)[:n] for f in bright[:4]), bright.n_above)
    expected = replace_with_billboards(frame, listed, bank, psf_index=jnp.arange(n))
    np.testing.assert_allclose(out, expected, rtol=1e-5, atol=1e-5)


def test_a_fixed_mask_gives_every_light_the_same_psf():
    model = _eye("fixed")
    frame = _frame()
    bright = bright_pixel_list(jnp.asarray(frame), 100.0, 8)
    out = render_position_glare(model, frame, bright, SCALE, 99, progress=False)
    psf = resample_psf(eqx.filter_jit(lambda m: m())(model), 0.003, SCALE, 17)
    np.testing.assert_allclose(
        out, replace_with_billboards(frame, bright, psf), rtol=1e-5, atol=1e-5
    )


def test_render_command_renders_position_masking_with_billboards_only(tmp_path):
    config = tmp_path / "eye_position.toml"
    config.write_text(_eye_toml("position"))
    scene = tmp_path / "lights.exr"
    write_exr(scene, _frame(), pixel_scale_deg=SCALE)
    runner = CliRunner()
    out = tmp_path / "glare.exr"
    args = ["render", str(scene), "--model", str(config), "--out", str(out)]
    result = runner.invoke(app, [*args, "--mode", "billboard", "--threshold", "100"])
    assert result.exit_code == 0, result.output
    model = build_model(load_toml(config))
    frame = _frame()
    expected = render_position_glare(
        model, frame, bright_pixel_list(jnp.asarray(frame), 100.0, 256), SCALE, 99, progress=False
    )
    np.testing.assert_allclose(read_exr(out).data, expected, rtol=1e-5, atol=1e-5)
    refused = runner.invoke(app, args)  # the default mode is convolve
    assert refused.exit_code == 2
    assert "masking = 'position'" in refused.output and "--mode billboard" in refused.output


def test_render_png_with_the_kakimoto_tone_map_exposes_for_the_glare_layer(tmp_path):
    """--tonemap kakimoto: the brightest light's glare plateau at white, its spot saturated
    (Kakimoto sec. 3.3), the PNG equal to the tone map of the linear render within 1/255."""
    from PIL import Image

    from invglare.commands.render import psf_at_scale
    from invglare.render import kakimoto_scene_scale, kakimoto_tonemap

    config = tmp_path / "eye_fixed.toml"
    config.write_text(_eye_toml("fixed"))
    scene = tmp_path / "lights.exr"
    write_exr(scene, _frame(), pixel_scale_deg=SCALE)
    runner = CliRunner()
    common = ["render", str(scene), "--model", str(config), "--mode", "billboard"]
    assert runner.invoke(app, [*common, "--out", str(tmp_path / "lin.exr")]).exit_code == 0
    result = runner.invoke(
        app, [*common, "--tonemap", "kakimoto", "--out", str(tmp_path / "k.png")]
    )
    assert result.exit_code == 0, result.output
    png = np.asarray(Image.open(tmp_path / "k.png"), dtype=float) / 255.0
    linear = read_exr(tmp_path / "lin.exr").data
    model = _eye("fixed")
    psf = psf_at_scale(model, SCALE, 99)
    radius = float(model.central_spot_radius_px()) * 0.003 / SCALE
    scale = kakimoto_scene_scale(psf, radius, 900.0)
    np.testing.assert_allclose(png, kakimoto_tonemap(linear, scale), atol=1 / 255 + 1e-6)
    # Not the exposure of the spot: the brightest light's surroundings are not black.
    row, col = 5, 8
    ring = png[row - 2 : row + 3, col - 2 : col + 3].copy()
    ring[1:4, 1:4] = np.nan
    assert png[row, col] == 1.0 and np.nanmax(ring) > 0.5
