"""A new model kind is one file and one registration: the recipe of CONTRIBUTING.md, followed.

`ToyGlare` (a Gaussian halo) and its reader live in this test only. Registered with one
line, it is computed by ``invglare psf``, rendered by ``invglare render``, used for a
synthetic photo by ``invglare synth``, fitted by ``invglare fit`` and round-tripped
through its config, without any other file of invglare knowing about it.
"""

import json
import math
from pathlib import Path
from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from jaxtyping import Array, Float
from typer.testing import CliRunner

from invglare.cli import app
from invglare.config.model import build_model, model_kinds, register_model_kind
from invglare.config.raster import GridRequest, square_npix
from invglare.config.section import Section, check_sections
from invglare.files.exr import read_exr, write_exr
from invglare.models.base import (
    AbstractGlareModel,
    broadcast_image,
    check_no_state,
    light_angle,
    light_angles,
)

# ---------------------------------------------------------------------------- the model file


class ToyGlare(AbstractGlareModel):
    """A circular Gaussian halo of width `sigma_deg`, unit energy on an `npix` grid."""

    sigma_deg: Float[Array, ""] = eqx.field(converter=jnp.asarray)
    npix: int = eqx.field(static=True)
    pixel_scale_deg: float = eqx.field(static=True)
    centre: ClassVar[str] = "light"
    animated: ClassVar[bool] = False

    def __call__(self, light_angle_deg=None, *, state=None):
        light_angle(light_angle_deg)
        check_no_state(self, state)
        c = (jnp.arange(self.npix) - self.npix // 2) * self.pixel_scale_deg
        r2 = c[:, None] ** 2 + c[None, :] ** 2
        halo = jnp.exp(-0.5 * r2 / self.sigma_deg**2)
        return halo / jnp.sum(halo)

    def batch(self, light_angles_deg, batch_size=None):
        return broadcast_image(self(), light_angles(light_angles_deg).shape[0])

    @property
    def wavelengths_nm(self):
        return None

    @property
    def shift_invariant(self) -> bool:
        return True

    def core_radius_px(self):
        return None

    def header(self) -> dict[str, Any]:
        return {"psfNormalisation": "unit energy over the grid"}

    def sized_for(self, others):
        return self

    def to_config(self) -> dict[str, Any]:
        return {
            "model": {"kind": "toy", "sigma_deg": float(self.sigma_deg)},
            "output": {"npix": self.npix, "pixel_scale_deg": self.pixel_scale_deg},
        }


def read_toy(config, base_dir=None, grid=GridRequest(), source="config") -> ToyGlare:
    check_sections(config, ("model", "output"), source)
    model = Section(config["model"], "model")
    model.get("kind", str)
    sigma = model.get("sigma_deg", float)
    model.finish()
    output = Section(config.get("output", {}), "output")
    n = output.get("npix", int, 64)
    scale = output.get("pixel_scale_deg", float, 0.01)
    output.finish()
    n = square_npix(grid.npix, source) or n
    scale = scale if grid.pixel_scale_deg is None else float(grid.pixel_scale_deg)
    return ToyGlare(sigma, n, scale)


# ---------------------------------------------------------------------------- its registration

register_model_kind("toy", ToyGlare, read_toy)

# ---------------------------------------------------------------------------- the tests

runner = CliRunner()


def _invoke(*args):
    result = runner.invoke(app, [str(a) for a in args])
    assert result.exit_code == 0, result.output + repr(result.exception)
    return result


@pytest.fixture
def toy_config(tmp_path) -> Path:
    path = tmp_path / "toy.toml"
    path.write_text(
        '[model]\nkind = "toy"\nsigma_deg = 0.05\n\n[output]\nnpix = 48\npixel_scale_deg = 0.01\n'
    )
    return path


def test_the_kind_is_registered_and_round_trips():
    assert "toy" in model_kinds()
    model = build_model({"model": {"kind": "toy", "sigma_deg": 0.04}})
    again = build_model(model.to_config())
    assert again.to_config() == model.to_config()
    np.testing.assert_array_equal(np.asarray(again()), np.asarray(model()))


def test_psf_command_writes_the_toy_psf(toy_config, tmp_path):
    out = tmp_path / "psf.exr"
    _invoke("psf", toy_config, "--out", out)
    img = read_exr(out)
    assert img.pixel_scale_deg == pytest.approx(0.01)
    assert img.data.shape == (48, 48)
    # Unit energy, peak at the centre, width sigma: the model's own image.
    assert float(img.data.sum()) == pytest.approx(1.0, rel=1e-5)
    r2 = ((np.arange(48) - 24) * 0.01) ** 2
    expected = np.exp(-0.5 * (r2[:, None] + r2[None, :]) / 0.05**2)
    np.testing.assert_allclose(img.data, expected / expected.sum(), rtol=1e-4, atol=1e-9)


def test_render_command_convolves_a_scene_with_the_toy_psf(toy_config, tmp_path):
    scene = np.zeros((64, 64), np.float32)
    scene[32, 32] = 1000.0
    scene_path = tmp_path / "scene.exr"
    write_exr(scene_path, scene, pixel_scale_deg=0.01)
    out = tmp_path / "out.exr"
    _invoke("render", scene_path, "--model", toy_config, "--out", out)
    # FFT convolution leaves round-off (~1e-9 of the peak) around zero.
    result = read_exr(out, allow_negative=True).data
    assert result.min() > -1e-6
    # The light is spread by the halo (sigma = 5 px), its energy kept within the frame.
    assert float(result.sum()) == pytest.approx(1000.0, rel=1e-4)
    assert result[32, 32] == pytest.approx(1000.0 / (2 * math.pi * 25.0), rel=1e-3)
    assert result[32, 37] == pytest.approx(result[32, 32] * math.exp(-0.5), rel=1e-3)


@pytest.mark.slow
def test_synth_and_fit_recover_the_toy_width(toy_config, tmp_path):
    spec = tmp_path / "toy_photo.toml"
    spec.write_text(
        f'[synth]\nmodel = "{toy_config}"\nseed = 11\n\n'
        '[set]\n"model.sigma_deg" = 0.062\n\n'
        "[observation]\nflux = 4e6\nbackground = 15.0\ngain = 2.0\nread_noise = 3.0\n"
    )
    _invoke("synth", spec, "--out-dir", tmp_path)
    photo = tmp_path / "toy_photo.exr"
    fit_config = tmp_path / "toy_fit.toml"
    fit_config.write_text(
        f'[fit]\nout_dir = "{tmp_path / "report"}"\n\n'
        f'[target]\nfile = "{photo}"\n\n[model]\nconfig = "{toy_config}"\n\n'
        "[observation]\ngain = 2.0\nread_noise = 3.0\n\n"
        '[[free]]\npath = "model.sigma_deg"\nlower = 0.02\nupper = 0.12\n\n'
        '[[free]]\npath = "obs.flux"\nlower = 0.0\nupper = inf\n\n'
        '[[free]]\npath = "obs.background"\nlower = -100.0\nupper = 1000.0\n\n'
        '[views]\npixels = 1.0\n\n[solver]\nn_starts = 2\nmax_steps = 60\n'
    )
    _invoke("fit", fit_config)
    params = json.loads((tmp_path / "report" / "params.json").read_text())
    sigma = params["parameters"]["model.sigma_deg"]
    assert sigma["value"] == pytest.approx(0.062, abs=3 * sigma["stderr"] + 1e-4)
    assert sigma["stderr"] < 0.002
