"""GlarePSF and Glare: gradients, equality with invglare's own functions, state, modes, errors."""

from __future__ import annotations

from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
from helpers import x64
from torch.func import functional_call
from torch_models import disk_config, eye_config

from invglare.config.model import build_model
from invglare.errors import ConfigError, InputDataError
from invglare.files.toml import load_toml
from invglare.fit import Parameter, ParameterSpace
from invglare.render.billboard import replace_with_billboards
from invglare.render.bright import bright_pixel_list
from invglare.render.convolve import convolve_psf, resample_psf
from invglare.render.ghost_frames import render_ghosts
from invglare.render.position_glare import render_position_glare
from invglare.torch import Glare, GlarePSF

DIAMETER = [{"path": "aperture.shapes[0].diameter_mm", "lower": 2.0, "upper": 4.9, "init": 3.7}]
EYE_FREE = [
    {"path": "aperture.pupil.diameter_mm", "lower": 2.0, "upper": 4.5, "init": 3.1},
    {"path": "aperture.upper_lashes.count", "lower": 4.0, "upper": 12.0, "init": 9.6},
]


@pytest.fixture(scope="module")
def disk_psf():
    return GlarePSF(disk_config(16), DIAMETER, dtype=torch.float64)


@pytest.fixture(scope="module")
def position_glare():
    """A masking = 'position' eye at its own pixel scale: each light its own PSF."""
    return Glare(eye_config("position"), EYE_FREE[:1], max_lights=2, dtype=torch.float64)


def _two_lights(h=12, w=12, channels=1, dtype=torch.float64):
    g = torch.Generator().manual_seed(5)
    image = 0.1 + torch.rand(1, channels, h, w, dtype=dtype, generator=g)
    image[0, :, h // 4, w // 3] = 50.0
    image[0, :, 2 * h // 3, 3 * w // 4] = 30.0
    return image


# --------------------------------------------------------------------------------------
# gradients


def test_gradcheck_psf_wrt_parameters(disk_psf):
    def psf_of(latent):
        return functional_call(disk_psf, {"latent": latent}, ())

    assert torch.autograd.gradcheck(psf_of, (disk_psf.latent.detach().clone().requires_grad_(),))


def test_gradcheck_convolution_wrt_images_and_parameters():
    glare = Glare(disk_config(16), DIAMETER, dtype=torch.float64)
    images = torch.rand(2, 3, 6, 7, dtype=torch.float64, generator=torch.Generator().manual_seed(1))

    def out(latent, images):
        return functional_call(glare, {"psf.latent": latent}, (images,))

    latent = glare.psf.latent.detach().clone().requires_grad_()
    assert torch.autograd.gradcheck(out, (latent, images.requires_grad_()))


@pytest.mark.slow
def test_gradcheck_billboards_wrt_images_and_parameters(position_glare):
    images = _two_lights(8, 8)

    def out(latent, images):
        return functional_call(position_glare, {"psf.latent": latent}, (images,))

    latent = position_glare.psf.latent.detach().clone().requires_grad_()
    assert torch.autograd.gradcheck(out, (latent, images.requires_grad_()), atol=1e-7)


def _grad_against_jax(config: dict, free: list[dict], size: int) -> None:
    psf = GlarePSF(config, free, dtype=torch.float64)
    weights = np.random.default_rng(2).random((size, size))
    out = psf()
    out[0].backward(torch.tensor(weights))
    with x64():
        model = build_model(config)
        space = ParameterSpace([Parameter(e["path"], e["lower"], e["upper"], init=e["init"])
                                for e in free])  # fmt: skip

        def loss(z):
            return jnp.sum(space.apply(model, space.from_latent(z))() * weights)

        grad = jax.grad(loss)(space.initial_latent())
    np.testing.assert_allclose(psf.latent.grad.numpy(), np.asarray(grad), rtol=1e-6)


def test_psf_gradient_equals_jax_gradient():
    """d(sum w * PSF)/d(latent): the layer against jax.grad of the same function."""
    free = [*DIAMETER, {"path": "aperture.shapes[0].center_mm[0]", "lower": -0.4, "upper": 0.4,
                        "init": 0.1}]  # fmt: skip
    _grad_against_jax(disk_config(16), free, 16)


@pytest.mark.slow
def test_eye_psf_gradient_equals_jax_gradient():
    _grad_against_jax(eye_config(), EYE_FREE, 32)


# --------------------------------------------------------------------------------------
# the same numbers as invglare's own functions


def test_psf_is_the_models_psf_channels_first():
    layer = GlarePSF(disk_config(16, rgb=True))
    model = build_model(disk_config(16, rgb=True))
    with torch.no_grad():
        out = layer()
    assert out.shape == (3, 16, 16) and layer.channels == 3
    np.testing.assert_allclose(out.numpy(), np.moveaxis(np.asarray(model()), -1, 0), rtol=1e-6)


def test_psf_resampled_to_an_image_scale():
    layer = GlarePSF(disk_config(32), pixel_scale_deg=0.01)
    model = build_model(disk_config(32))
    own = float(model.propagator.output.pixel_scale_deg)
    with torch.no_grad():
        out = layer()
    n = out.shape[-1]
    assert n % 2 == 1 and layer.output_scale_deg == 0.01
    expected = resample_psf(model(), own, 0.01, n)
    np.testing.assert_allclose(out[0].numpy(), np.asarray(expected), rtol=1e-5, atol=1e-9)
    assert abs(float(out.sum()) - float(model().sum())) < 1e-5  # energy kept


def test_convolution_equals_convolve_psf():
    glare = Glare(disk_config(16))
    images = torch.rand(2, 3, 10, 12)
    with torch.no_grad():
        out = glare(images)
        psf = glare.psf()[0].numpy()
    for b in range(2):
        expected = convolve_psf(images[b].permute(1, 2, 0).numpy(), psf)
        np.testing.assert_allclose(out[b].permute(1, 2, 0).numpy(), expected, rtol=1e-5, atol=1e-6)


@pytest.mark.slow
def test_billboards_equal_the_position_render(position_glare):
    images = _two_lights(12, 12, channels=3)
    with torch.no_grad():
        out = position_glare(images)[0].permute(1, 2, 0).numpy()
    with x64():
        model = position_glare.psf.model_at()
        image = jnp.asarray(images[0].permute(1, 2, 0).numpy())
        bright = bright_pixel_list(image, float(jnp.max(image[..., 1])) / 100.0, 2)
        expected = render_position_glare(model, image, bright, position_glare.pixel_scale_deg, 33)
    assert position_glare.mode == "billboard"
    np.testing.assert_allclose(out, np.asarray(expected), rtol=1e-6, atol=1e-9)


def test_billboards_of_a_shift_invariant_model_use_its_one_psf():
    glare = Glare(disk_config(16), mode="billboard", max_lights=2, threshold=10.0)
    images = _two_lights(12, 12, channels=3, dtype=torch.float32)
    with torch.no_grad():
        out = glare(images)[0].permute(1, 2, 0).numpy()
        psf = glare.psf()[0].numpy()
    image = images[0].permute(1, 2, 0).numpy()
    expected = replace_with_billboards(image, bright_pixel_list(image, 10.0, 2), psf)
    np.testing.assert_allclose(out, np.asarray(expected), rtol=1e-6, atol=1e-7)


def _veiling_config() -> dict:
    """The example's five ghosts on a 16 x 16 screen of 1 deg/px (the images' grid)."""
    config = load_toml(Path(__file__).resolve().parents[2] / "examples" / "veiling_ghosts.toml")
    config["output"] = {"npix": 16, "pixel_scale_deg": 1.0}
    config["model"]["n_harmonics"] = 16
    return config


def test_ghosts_equal_render_ghosts_and_gradcheck():
    free = [{"path": "ghosts.radius_deg[0]", "lower": 0.5, "upper": 4.0}]
    glare = Glare(_veiling_config(), free, max_lights=2, dtype=torch.float64)
    assert glare.mode == "ghosts"
    images = _two_lights(16, 16, channels=3)
    with torch.no_grad():
        out = glare(images)[0].permute(1, 2, 0).numpy()
    with x64():
        image = jnp.asarray(images[0].permute(1, 2, 0).numpy())
        bright = bright_pixel_list(image, float(jnp.max(image[..., 1])) / 100.0, 2)
        expected = render_ghosts(glare.psf.model_at(), image, bright, 1.0)
    np.testing.assert_allclose(out, np.asarray(expected), rtol=1e-9, atol=1e-12)

    def of(latent, images):
        return functional_call(glare, {"psf.latent": latent}, (images,))

    latent = glare.psf.latent.detach().clone().requires_grad_()
    assert torch.autograd.gradcheck(of, (latent, _two_lights(16, 16, 1).requires_grad_()))


def test_images_in_any_layout_give_the_same_glare():
    glare = Glare(disk_config(16), DIAMETER)
    base = torch.rand(2, 3, 9, 10)
    images = [
        base,
        base.to(memory_format=torch.channels_last),
        base.transpose(2, 3).contiguous().transpose(2, 3),
    ]
    outs = []
    for im in images:
        im = im.clone().requires_grad_()
        out = glare(im)
        out.backward(torch.ones_like(out))
        outs.append((out.detach(), im.grad))
    for out, grad in outs[1:]:
        torch.testing.assert_close(out, outs[0][0], rtol=0, atol=0)
        torch.testing.assert_close(grad, outs[0][1], rtol=0, atol=0)


# --------------------------------------------------------------------------------------
# parameters, state, modes, precision


def test_parameters_are_latent_with_physical_values():
    psf = GlarePSF(eye_config(), EYE_FREE)
    assert psf.paths == ("aperture.pupil.diameter_mm", "aperture.upper_lashes.count")
    np.testing.assert_allclose(list(psf.values().values()), [3.1, 9.6], rtol=1e-6)
    with torch.no_grad():
        psf.latent.fill_(50.0)  # far out in latent space: the bounds still hold
    np.testing.assert_allclose(psf.physical.detach().numpy(), [4.5, 12.0], rtol=1e-6)
    psf.set_values({"aperture.pupil.diameter_mm": 2.5, "aperture.upper_lashes.count": 5.0})
    np.testing.assert_allclose(list(psf.values().values()), [2.5, 5.0], rtol=1e-5)


def test_fit_style_paths_and_parameters_are_accepted():
    a = GlarePSF(disk_config(16), [{"path": "model.aperture.shapes[0].diameter_mm",
                                    "lower": 2.0, "upper": 4.9}])  # fmt: skip
    b = GlarePSF(disk_config(16), [Parameter("aperture.shapes[0].diameter_mm", 2.0, 4.9, 4.0)])
    assert a.paths == b.paths == ("aperture.shapes[0].diameter_mm",)
    assert a.values() == pytest.approx({"aperture.shapes[0].diameter_mm": 4.0})


def test_state_dict_round_trip():
    a = Glare(disk_config(16), DIAMETER)
    a.psf.set_values([2.6])
    b = Glare(disk_config(16), DIAMETER)
    b.load_state_dict(a.state_dict())
    assert b.psf.values() == pytest.approx({"aperture.shapes[0].diameter_mm": 2.6})
    with torch.no_grad():
        torch.testing.assert_close(a.psf(), b.psf())
    other = Glare(disk_config(16), [{"path": "aperture.shapes[0].center_mm[0]", "lower": -1,
                                     "upper": 1}])  # fmt: skip
    with pytest.raises(ConfigError, match="saved with the free parameters"):
        other.load_state_dict(a.state_dict())


def test_to_float64_makes_every_call_float64():
    psf = GlarePSF(disk_config(16), DIAMETER)
    out32 = psf().detach()
    psf.to(torch.float64)
    out64 = psf()
    out64.sum().backward()
    assert out32.dtype == torch.float32 and out64.dtype == torch.float64
    assert psf.latent.grad.dtype == torch.float64
    torch.testing.assert_close(out64.detach().float(), out32, rtol=1e-4, atol=1e-7)
    glare = Glare(disk_config(16), DIAMETER).double()
    assert glare(torch.rand(1, 3, 5, 5, dtype=torch.float64)).dtype == torch.float64


def test_eval_keeps_the_psf_while_the_parameters_are_unchanged():
    psf = GlarePSF(disk_config(16), DIAMETER)
    calls = []
    inner = psf._psf
    psf._psf = lambda latent: calls.append(1) or inner(latent)
    train = psf()
    psf()
    assert len(calls) == 2  # train mode: every call computes
    psf.eval()
    with torch.no_grad():
        kept = psf()
        again = psf()
        assert len(calls) == 3 and again is kept
        torch.testing.assert_close(kept, train.detach())
        psf.set_values([3.0])  # new values: computed again
        psf()
        assert len(calls) == 4
    psf()  # a gradient is wanted: computed, not kept
    assert len(calls) == 5 and not psf.training


def test_glare_in_eval_convolves_with_the_kept_psf():
    glare = Glare(disk_config(16), DIAMETER)
    images = torch.rand(2, 3, 8, 8)
    trained = glare(images).detach()  # train mode: PSF and convolution in one call
    fused, psf_calls = glare._psf_convolve, []
    glare._psf_convolve = lambda *a: pytest.fail("eval without a gradient recomputed the PSF")
    inner = glare.psf._psf
    glare.psf._psf = lambda latent: psf_calls.append(1) or inner(latent)
    glare.eval()
    with torch.no_grad():
        first, second = glare(images), glare(images)
    assert len(psf_calls) == 1
    torch.testing.assert_close(first, trained, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(second, first, rtol=0, atol=0)
    glare._psf_convolve = fused
    glare(images).sum().backward()  # eval with a gradient: the fused call again
    assert glare.psf.latent.grad is not None


# --------------------------------------------------------------------------------------
# bad input


def test_unknown_path_lists_the_valid_ones():
    with pytest.raises(
        ConfigError,
        match=r"does not exist\. Did you mean 'aperture\.pupil\.diameter_mm'.*Valid paths: ",
    ):
        GlarePSF(eye_config(), [{"path": "aperture.pupil.diametre_mm", "lower": 2, "upper": 4}])


@pytest.mark.parametrize(
    ("entry", "message"),
    [
        ({"path": "aperture.shapes[0].diameter_mm", "lower": 2.0}, "needs the key 'upper'"),
        (
            {"path": "aperture.shapes[0].diameter_mm", "lower": 2, "upper": 5, "prior": "x"},
            "unknown key 'prior'",
        ),
        (
            {"path": "aperture.shapes[0].diameter_mm", "lower": 4.5, "upper": 4.9},
            r"init 4 is not strictly inside the bounds \[4.5, 4.9\]",
        ),
        ("aperture.shapes[0].diameter_mm", "must be a Parameter or a table"),
    ],
)
def test_bad_free_entries(entry, message):
    with pytest.raises(ConfigError, match=message):
        GlarePSF(disk_config(16), [entry])


def test_bad_images_are_refused():
    glare = Glare(disk_config(16))
    with pytest.raises(
        InputDataError, match=r"\(B, C, H, W\), got \(3, 8, 8\) \(one image: images\[None\]\)"
    ):
        glare(torch.rand(3, 8, 8))
    with pytest.raises(InputDataError, match=r"1 or 3 channels .* got shape \(1, 4, 8, 8\)"):
        glare(torch.rand(1, 4, 8, 8))
    with pytest.raises(InputDataError, match=r"has dtype torch\.int64; expected float32"):
        glare(torch.ones(1, 3, 8, 8, dtype=torch.int64))
    bad = torch.rand(1, 3, 8, 8)
    bad[0, 2, 5, 1] = float("nan")
    with pytest.raises(InputDataError, match=r"images\) has 1 non-finite .* \(0, 2, 5, 1\)"):
        glare(bad)
    rgb = Glare(disk_config(16, rgb=True))
    with pytest.raises(InputDataError, match=r"RGB model takes images with 3 channels"):
        rgb(torch.rand(1, 1, 8, 8))


def test_bad_layer_options_are_refused():
    with pytest.raises(ConfigError, match="a convolution cannot render it; use mode = 'billboard'"):
        Glare(eye_config("position"), mode="convolve")
    with pytest.raises(ConfigError, match="mode 'blur' is not one of"):
        Glare(disk_config(16), mode="blur")
    with pytest.raises(ConfigError, match="max_lights must be an integer >= 1"):
        Glare(eye_config("position"), max_lights=0)
    with pytest.raises(ConfigError, match=r"dtype must be torch\.float32 or torch\.float64"):
        GlarePSF(disk_config(16), dtype=torch.float16)
    with pytest.raises(ConfigError, match="expected a model config"):
        GlarePSF(42)
    with pytest.raises(ConfigError, match="does not exist"):
        GlarePSF("no/such/model.toml")


def test_a_built_model_is_used_as_it_is():
    model = build_model(disk_config(16))
    layer = GlarePSF(model, DIAMETER)
    assert layer.model is model
    at = layer.model_at()
    assert float(at.aperture.shapes[0].diameter_mm) == pytest.approx(3.7)
    assert float(model.aperture.shapes[0].diameter_mm) == 4.0  # the given model is unchanged
    assert eqx.tree_equal(
        eqx.tree_at(
            lambda m: m.aperture.shapes[0].diameter_mm, at, model.aperture.shapes[0].diameter_mm
        ),
        model,
    )
