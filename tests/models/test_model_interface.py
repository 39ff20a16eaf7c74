"""Every built-in model kind through the one interface of `invglare.models.base`.

For each kind, built from a small config by `invglare.config.model.build_model`: `jit`
equals eager, `vmap` over light directions equals a loop and `model.batch`, the gradient
of a scalar of the image with respect to one float leaf matches central differences in
float64 (converging over two steps), `to_config()` rebuilds the same model, and the
interface's properties have their documented values.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import assert_grad_converges, x64

from invglare.config.model import build_model, model_kind
from invglare.errors import ConfigError
from invglare.models.base import AbstractGlareModel
from invglare.optics.spectral import parse_wavelengths

#: Light directions (deg) for the vmap / loop / batch comparison: on axis and off axis.
ANGLES = ((0.0, 0.0), (1.0, 0.5), (-2.0, 1.5))
#: The light of the gradient check: off axis, so that the position-masked and veiling
#: models' images depend on where the light is.
GRAD_ANGLE = (1.0, 0.5)


def fft_native_scale_deg(config: dict[str, Any], wavelength_nm: float) -> float:
    """The FFT's native pixel scale of `make_propagator`: ``lambda / (fft_npix * pitch)``
    with ``fft_npix = max(npix, 2 * aperture_npix)`` (even) and ``pitch = window / n``."""
    table = config["model"]
    n = table["aperture_npix"]
    fft_npix = max(config["output"]["npix"], 2 * n)
    fft_npix += fft_npix % 2
    return math.degrees(wavelength_nm * 1e-6 / (fft_npix * table["window_mm"] / n))


@dataclasses.dataclass(frozen=True)
class Kind:
    """A kind's small config, the leaf its gradient is checked for, and the documented
    values of its interface."""

    config: dict[str, Any]
    leaf: Callable[[Any], Any]  # the model -> the float leaf (a scalar, or a vector's [0])
    leaf_index: int | None  # None: a scalar leaf; else the element of a vector leaf
    x0: float  # the leaf's value in the config
    eps: float  # the larger central-difference step (the smaller is eps / 4)
    pixel_scale_deg: Callable[[dict[str, Any]], float]  # of the written config
    wavelengths_nm: tuple[float, ...] | None
    shift_invariant: bool
    centre: str
    animated: bool
    channels: int | None  # None: (ny, nx); 3: (ny, nx, 3)


KINDS = {
    # A 3 mm disk, one wavelength, an explicit pixel scale (the MFT).
    "aperture": Kind(
        config={
            "model": {
                "kind": "aperture",
                "focal_length_mm": 17.0,
                "aperture_npix": 32,
                "shapes": [{"kind": "disk", "diameter_mm": 3.0}],
            },
            "output": {"npix": 32, "pixel_scale_deg": 0.008},
            "spectrum": {"wavelengths_nm": 550.0},
        },
        leaf=lambda m: m.aperture.shapes[0].diameter_mm,
        leaf_index=None,
        x0=3.0,
        eps=5e-4,  # per unit closed-form area pi D^2 / 4: at 1e-3 truncation is 2e-5
        pixel_scale_deg=lambda c: 0.008,
        wavelengths_nm=(550.0,),
        shift_invariant=True,
        centre="light",
        animated=False,
        channels=None,
    ),
    # The eye with lids and lashes, the fixed mask (eq. 5), the FFT's native pixel scale.
    "eye": Kind(
        config={
            "model": {
                "kind": "eye",
                "aperture_npix": 48,
                "eye": {
                    "seed": 3,
                    "pupil": {"diameter_mm": 3.0},
                    "lids": {"upper_opening_mm": 1.3},
                    "lashes_upper": {"count": 6, "length_mm": 2.0, "thickness_mm": 0.08},
                },
            },
            "output": {"npix": 32},
            "spectrum": {"wavelengths_nm": 550.0},
        },
        leaf=lambda m: m.aperture.pupil.diameter_mm,
        leaf_index=None,
        x0=3.0,
        eps=2e-4,
        pixel_scale_deg=lambda c: fft_native_scale_deg(c, 550.0),
        wavelengths_nm=(550.0,),
        shift_invariant=True,
        centre="light",
        animated=False,
        channels=None,
    ),
    # A camera whose cross-screen filter's image moves with the light (eq. 3), paper RGB.
    "camera": Kind(
        config={
            "model": {
                "kind": "camera",
                "aperture_npix": 48,
                "obstacle_distance_mm": 5.0,
                "masking": "position",
                "colour": "paper_rgb",
                "camera": {
                    "diaphragm": {"n_blades": 6, "f_number": 8.0, "focal_length_mm": 50.0},
                    "cross_screen": {
                        "angles_deg": [0.0, 60.0],
                        "spacing_mm": 0.4,
                        "duty_cycle": 0.1,
                    },
                },
            },
            "output": {"npix": 32, "pixel_scale_deg": 0.003},
        },
        leaf=lambda m: m.aperture.diaphragm.f_number,
        leaf_index=None,
        x0=8.0,
        eps=5e-4,  # per unit open area: at 1.5e-3 truncation is 5e-5 of the gradient
        pixel_scale_deg=lambda c: 0.003,
        wavelengths_nm=(680.0, 530.0, 460.0),
        shift_invariant=False,
        centre="light",
        animated=False,
        channels=3,
    ),
    # Two hand-made ghosts moving at their own rates with the light.
    "veiling": Kind(
        config={
            "model": {
                "kind": "veiling",
                "profile": "hat",
                "n_harmonics": 16,
                # The raw series: the positivity floor's kink, where a ringing pixel sits
                # within a difference step of 0, stops central differences converging.
                "positivity": "none",
                "ghosts": {
                    "position_deg": [[0.0, 0.0], [0.5, 0.0]],
                    "radius_deg": [1.5, 3.0],
                    "intensity_per_sr": [0.02, 0.006],
                    "softness_deg": 0.3,
                    "ratio": [-0.4, 0.3],
                },
            },
            "output": {"npix": 32, "pixel_scale_deg": 0.3},
        },
        leaf=lambda m: m.ghosts.radius_deg,
        leaf_index=0,
        x0=1.5,
        eps=1e-3,
        pixel_scale_deg=lambda c: 0.3,
        wavelengths_nm=None,
        shift_invariant=False,
        centre="axis",
        animated=False,
        channels=None,
    ),
    # The dynamic eye: a pupil only (the smallest compile), 8 wavelengths by scaled copies.
    "temporal": Kind(
        config={
            "model": {
                "kind": "temporal",
                "aperture_npix": 32,
                "seed": 2,
                "eye": {"seed": 3, "pupil": {"diameter_mm": 5.0}},
                # The mean pupil is the eye's own (not the luminance's): a leaf to vary.
                "dynamics": {"pupil": {"from_luminance": False}},
            },
            "output": {"npix": 32},
            "spectrum": {"wavelengths_nm": "380:770:8"},
        },
        leaf=lambda m: m.eye.pupil.diameter_mm,
        leaf_index=None,
        x0=5.0,
        eps=1e-3,
        # Eq. 3 at the eye's distance: the retina at the aperture pitch, pitch / d rad.
        pixel_scale_deg=lambda c: math.degrees(
            c["model"]["window_mm"] / c["model"]["aperture_npix"] / c["model"]["focal_length_mm"]
        ),
        wavelengths_nm=tuple(float(w) for w in parse_wavelengths("380:770:8")),
        shift_invariant=True,
        centre="light",
        animated=True,
        channels=3,
    ),
}


def _image(model: AbstractGlareModel, angle) -> jax.Array:
    return model(angle)


# Compiled once per model structure: the loop over lights and the rebuilt model reuse it.
JIT_IMAGE = jax.jit(_image)
JIT_VMAP = jax.jit(jax.vmap(_image, in_axes=(None, 0)))
# batch under jit: eagerly, its vmap and lax.map run op by op (half a minute each for the
# camera on a loaded 2-core machine, against a few seconds to compile).
JIT_BATCH = jax.jit(lambda m, angles: m.batch(angles))
JIT_BATCH_CHUNKS = jax.jit(lambda m, angles: m.batch(angles, batch_size=2))
JIT_ADVANCE = jax.jit(lambda m, state: m.advance(state, m.field_luminance_cd_m2))


def _close(a, b, what: str) -> None:
    """float32 images computed by differently fused programs: equal to 1e-5 of the peak."""
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape, what
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-5 * float(np.abs(b).max()), err_msg=what)


@pytest.mark.parametrize("name", list(KINDS))
@pytest.mark.slow
def test_model_kind_works_under_jit_vmap_and_grad_and_round_trips(name):
    kind = KINDS[name]
    model = build_model(copy.deepcopy(kind.config))
    assert isinstance(model, AbstractGlareModel)
    assert isinstance(model, model_kind(name).model_class)

    # ---- the documented values of the interface
    written = model.to_config()
    assert written["model"]["kind"] == name
    assert float(model.pixel_scale_deg) == pytest.approx(kind.pixel_scale_deg(written), rel=1e-6)
    if kind.wavelengths_nm is None:
        assert model.wavelengths_nm is None
    else:
        assert model.wavelengths_nm == pytest.approx(kind.wavelengths_nm, rel=1e-6)
    assert model.shift_invariant is kind.shift_invariant
    assert model.centre == kind.centre and type(model).centre == kind.centre
    assert model.animated is kind.animated

    # ---- one light: eager, jit
    angles = jnp.asarray(ANGLES, dtype=jnp.float32)
    eager = model(angles[1])
    npix = written["output"]["npix"]
    expected_shape = (npix, npix) if kind.channels is None else (npix, npix, kind.channels)
    assert eager.shape == expected_shape and eager.dtype == jnp.float32
    assert np.all(np.isfinite(np.asarray(eager))) and float(jnp.max(eager)) > 0
    _close(JIT_IMAGE(model, angles[1]), eager, "jit")
    if kind.animated:
        # The resting state is the default; a later frame is another image.
        state = model.init_state()
        _close(model(angles[1], state=state), eager, "state at rest")
        later = JIT_ADVANCE(model, state)
        assert float(jnp.abs(model(angles[1], state=later) - eager).max()) > 0.0
    else:
        with pytest.raises(ConfigError, match="static model"):
            model(angles[1], state=0.0)

    # ---- many lights: vmap, a loop, batch (one vmap, and lax.map in chunks)
    loop = jnp.stack([JIT_IMAGE(model, a) for a in angles])
    _close(JIT_VMAP(model, angles), loop, "vmap")
    _close(JIT_BATCH(model, angles), loop, "batch")
    _close(JIT_BATCH_CHUNKS(model, angles), loop, "batch in chunks")
    moved = float(jnp.abs(loop[2] - loop[1]).max()) / float(jnp.abs(loop[1]).max())
    if kind.shift_invariant:
        assert moved == 0.0
    else:
        # Each light its own image (the camera's filter image moves by 0.45 % of the
        # peak between these two lights; float32 differences are ~1e-6).
        assert moved > 1e-3

    # ---- the config round trip
    again = build_model(written)
    assert type(again) is type(model)
    assert again.to_config() == written
    np.testing.assert_array_equal(
        np.asarray(JIT_IMAGE(again, angles[1])), np.asarray(JIT_IMAGE(model, angles[1]))
    )


@pytest.mark.parametrize("name", list(KINDS))
@pytest.mark.slow
def test_gradient_of_one_float_leaf_matches_central_differences_in_float64(name):
    kind = KINDS[name]
    with x64():
        model = build_model(copy.deepcopy(kind.config))
        angle = jnp.asarray(GRAD_ANGLE, dtype=jnp.float64)
        image = jax.eval_shape(model, angle)
        assert image.dtype == jnp.float64
        weights = jnp.asarray(np.random.default_rng(7).uniform(0.5, 1.5, image.shape))
        leaf = kind.leaf(model)
        assert leaf.dtype == jnp.float64
        assert float(leaf if kind.leaf_index is None else leaf[kind.leaf_index]) == kind.x0

        def loss(x):
            value = x if kind.leaf_index is None else leaf.at[kind.leaf_index].set(x)
            m = eqx.tree_at(kind.leaf, model, value)
            return jnp.sum(weights * m(angle))

        # One compilation for the gradient and the central differences' values.
        value_and_grad = jax.jit(jax.value_and_grad(loss))
        grad = float(value_and_grad(jnp.float64(kind.x0))[1])
        assert math.isfinite(grad) and grad != 0.0
        assert_grad_converges(
            lambda x: value_and_grad(x)[0], kind.x0, kind.eps, grad=grad, rtol=1e-5, err_msg=name
        )
