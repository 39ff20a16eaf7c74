"""GlareAugment: per-sample draws from config ranges, reproducible in DataLoader workers."""

from __future__ import annotations

import copy
import math
import pickle

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader
from torch_models import camera_config, eye_config

from invglare.errors import ConfigError, InputDataError, PhysicsRangeError
from invglare.torch import Glare, GlareAugment, GlareDataset

SCALE_DEG = 0.01


def _config(**augment) -> dict:
    eye = {
        "name": "eye",
        "model": eye_config(),
        "weight": 2.0,
        "draw": {
            "aperture.pupil.diameter_mm": [2.0, 4.0],
            "aperture.upper_lashes.count": {"low": 4, "high": 11, "integer": True},
            "aperture.upper_lashes.mean_angle_deg": [-10.0, 10.0],
            "aperture.particles[0].count": [0.0, 15.0],
        },
    }
    camera = {
        "name": "camera",
        "model": camera_config(),
        "draw": {
            "aperture.diaphragm.f_number": [7.2, 11.0],
            "aperture.filter.angles_deg[0]": [0.0, 45.0],
            "aperture.filter.spacing_mm": [0.8, 1.2],
        },
        "choose": {"model.camera.diaphragm.n_blades": [5, 6, 8]},
    }
    table = {"pixel_scale_deg": SCALE_DEG, "source": [eye, camera], **augment}
    return {"augment": table}


@pytest.fixture(scope="module")
def augment():
    return GlareAugment(_config(), seed=11, return_clean=True, return_params=True)


def _images(n=6, size=12, seed=0):
    g = torch.Generator().manual_seed(seed)
    images = 0.05 * torch.rand(n, 3, size, size, generator=g)
    images[:, :, size // 2, size // 2] = 200.0
    return images


def test_draws_depend_on_seed_epoch_and_index_only(augment):
    first = [augment.draw(i) for i in range(8)]
    assert [augment.draw(i) for i in range(8)] == first  # no hidden state
    assert first[0] != first[1]
    other = GlareAugment(_config(), seed=12)
    assert [other.draw(i) for i in range(8)] != first
    augment.set_epoch(1)
    try:
        assert [augment.draw(i) for i in range(8)] != first
    finally:
        augment.set_epoch(0)
    state = torch.random.get_rng_state()
    augment(_images(1)[0], index=3)
    assert torch.equal(torch.random.get_rng_state(), state)  # no global RNG used


def test_draws_cover_the_ranges_and_the_sources():
    augment = GlareAugment(_config(), seed=0)
    draws = [augment.draw(i) for i in range(300)]
    eyes = [d for d in draws if d["source"] == 0]
    cams = [d for d in draws if d["source"] == 1]
    assert 150 < len(eyes) < 250  # weights 2 : 1
    counts = {d["values"][1] for d in eyes}
    assert counts == set(map(float, range(4, 12)))  # integers, both ends included
    pupils = np.array([d["values"][0] for d in eyes])
    assert 2.0 <= pupils.min() < 2.2 and 3.8 < pupils.max() <= 4.0
    assert {d["choice"] for d in cams} == {(5,), (6,), (8,)}


def test_sample_holds_clean_glared_and_params(augment):
    image = _images(1)[0]
    sample = augment(image, index=4)
    assert set(sample) == {"glared", "clean", "params"}
    assert sample["clean"] is image and sample["glared"].shape == image.shape
    drawn = augment.draw(4)
    source = augment.sources[drawn["source"]]
    assert int(sample["params"]["source"]) == drawn["source"]
    for r, v in zip(source.draws, drawn["values"], strict=True):
        assert float(sample["params"][f"{source.name}/{r.path}"]) == pytest.approx(v, rel=1e-6)
    others = [k for k in augment.param_keys if k != "source" and not k.startswith(source.name)]
    assert others and all(math.isnan(float(sample["params"][k])) for k in others)
    # The glare spreads the light: the core is dimmer, its surroundings brighter.
    assert float(sample["glared"][1, 6, 6]) < 200.0 and float(sample["glared"][1, 6, 8]) > 0.06


def test_rendering_is_the_glare_layer_at_the_drawn_values(augment):
    image = _images(1, seed=3)[0]
    drawn = next(d for d in map(augment.draw, range(20)) if d["source"] == 0)
    index = next(i for i in range(20) if augment.draw(i) == drawn)
    source = augment.sources[0]
    free = [
        {"path": r.path, "lower": r.low, "upper": r.high, "init": v, "transform": "identity"}
        for r, v in zip(source.draws, drawn["values"], strict=True)
    ]
    layer = Glare(source.model, free, pixel_scale_deg=SCALE_DEG)
    with torch.no_grad():
        expected = layer(image[None])[0]
    torch.testing.assert_close(augment(image, index=index)["glared"], expected)


def test_batches_draw_consecutive_indices(augment):
    images = _images(3)
    batch = augment(images, index=10)
    for b in range(3):
        torch.testing.assert_close(batch["glared"][b], augment(images[b], index=10 + b)["glared"])
    assert batch["params"]["source"].shape == (3,)


def test_probability_zero_leaves_images_clean():
    augment = GlareAugment(_config(probability=0.0), return_params=True)
    image = _images(1)[0]
    sample = augment(image, index=0)
    torch.testing.assert_close(sample["glared"], image)
    assert int(sample["params"]["source"]) == -1


def test_pickled_augment_draws_and_renders_the_same(augment):
    copy_ = pickle.loads(pickle.dumps(augment))
    image = _images(1)[0]
    assert [copy_.draw(i) for i in range(5)] == [augment.draw(i) for i in range(5)]
    torch.testing.assert_close(copy_(image, index=2)["glared"], augment(image, index=2)["glared"])


def _batches(loader):
    return [(b["glared"].clone(), {k: v.clone() for k, v in b["params"].items()}) for b in loader]


@pytest.mark.slow
def test_dataloader_with_two_workers_is_reproducible():
    # One source keeps the workers' compilation short; spawn: JAX does not survive a fork.
    config = _config()
    config["augment"]["source"] = config["augment"]["source"][:1]
    dataset = GlareDataset(_images(6), GlareAugment(config, seed=5, return_params=True))
    loader = DataLoader(dataset, batch_size=2, num_workers=2, multiprocessing_context="spawn",
                        persistent_workers=True)  # fmt: skip
    runs = [_batches(loader), _batches(loader), _batches(DataLoader(dataset, batch_size=2))]
    for run in runs[1:]:
        for (g0, p0), (g1, p1) in zip(runs[0], run, strict=True):
            torch.testing.assert_close(g1, g0, rtol=0, atol=0)
            for key in p0:
                torch.testing.assert_close(p1[key], p0[key], rtol=0, atol=0, equal_nan=True)
    pupils = torch.cat([p["eye/aperture.pupil.diameter_mm"] for _, p in runs[0]])
    assert len(set(pupils.tolist())) == 6  # every sample its own eye


# --------------------------------------------------------------------------------------
# bad input


def _with(change) -> dict:
    config = copy.deepcopy(_config())
    change(config["augment"])
    return config


@pytest.mark.parametrize(
    ("change", "error", "message"),
    [
        (lambda a: a.pop("pixel_scale_deg"), ConfigError, "needs the key 'pixel_scale_deg'"),
        (lambda a: a.update(blur=1), ConfigError, "unknown key 'blur'"),
        (lambda a: a.update(probability=2.0), ConfigError, r"probability must lie in \[0, 1\]"),
        (lambda a: a.update(source=[]), ConfigError, "augment.source is empty"),
        (
            lambda a: a["source"][0]["draw"].update({"aperture.pupil.diametre_mm": [2, 3]}),
            ConfigError,
            "Did you mean 'aperture.pupil.diameter_mm'",
        ),
        (
            lambda a: a["source"][0]["draw"].update({"aperture.pupil.diameter_mm": [3.0, 2.0]}),
            ConfigError,
            "low 3 must be < high 2",
        ),
        (
            lambda a: a["source"][1]["choose"].update({"model.camera.blades": [5]}),
            ConfigError,
            "'model.camera.blades' is no key of the model config",
        ),
        (
            lambda a: a["source"][0]["draw"].update({"aperture.pupil.diameter_mm": [2.0, 6.0]}),
            PhysicsRangeError,
            "wider than the model's window",
        ),
        (lambda a: a["source"][1].update(weight=0), ConfigError, "weight must be > 0"),
    ],
)
def test_bad_configs(change, error, message):
    with pytest.raises(error, match=message):
        GlareAugment(_with(change))


def test_bad_images(augment):
    with pytest.raises(
        InputDataError, match=r"\(C, H, W\) or a batch \(B, C, H, W\), got \(8, 8\)"
    ):
        augment(torch.rand(8, 8), index=0)
    with pytest.raises(InputDataError, match=r"has dtype torch\.int64"):
        augment(torch.ones(3, 8, 8, dtype=torch.int64), index=0)
    with pytest.raises(ConfigError, match="one \\[augment\\] table"):
        GlareAugment({"augmentation": {}})
