"""Tests of fitted eyelash layouts (invglare.aperture.eye.lash_layout): a row carrying its
lashes' own values draws exactly what its key drew, reads and writes them in its config
table, differentiates in every per-lash value, and its prior is the distribution the key
draws from."""

from __future__ import annotations

import functools
import math

import equinox as eqx
import helpers
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from invglare._core.grids import ApertureGrid
from invglare.aperture.eye import EyeAperture, Eyelashes, Eyelids, Pupil, eye_to_config
from invglare.aperture.eye.lash_layout import LAYOUT_LEAVES, LashLayout, prior_moments
from invglare.config.eye import eye_from_config
from invglare.errors import ConfigError


def _eye(n_max: int = 6, count: float = 5.5) -> EyeAperture:
    """A 2 mm pupil under a lid 0.6 mm above the axis, with a short row of bent lashes."""
    lashes = Eyelashes(
        count=count,
        n_max=n_max,
        key=jax.random.key(11),
        lid="upper",
        mean_angle_deg=4.0,
        angular_spread_deg=10.0,
        thickness_mm=0.07,
        length_mm=1.4,
        curvature_per_mm=0.2,
        root_span_mm=1.8,
    )
    return EyeAperture(Pupil(2.0), Eyelids(0.6, 1.2), upper_lashes=lashes)


def _grid() -> ApertureGrid:
    return ApertureGrid.from_width(64, 2.2)


def test_frozen_layout_draws_the_same_lashes_1e12():
    """A row with its draw frozen into a layout rasterises as the key draws it: within
    1e-12 in float64 (the same values, computed once eagerly instead of inside the jitted
    raster; float32 rounds that differently by up to 1.8e-6)."""
    with helpers.x64():
        eye = _eye()
        frozen = eqx.tree_at(lambda e: e.upper_lashes, eye, eye.upper_lashes.with_layout())
        a, b = eye.transmission(_grid()), frozen.transmission(_grid())
        assert float(jnp.max(jnp.abs(a - b))) <= 1e-12
    assert frozen.upper_lashes.layout.size == 6


def test_layout_moves_one_lash_only():
    """Changing one lash's angle changes the pixels that lash covers, no others."""
    eye = _eye()
    row = eye.upper_lashes.with_layout()
    tilted = eqx.tree_at(lambda r: r.layout.angle_deg, row, row.layout.angle_deg.at[2].add(15.0))
    a = eqx.tree_at(lambda e: e.upper_lashes, eye, row).obstacle_transmission(_grid())
    b = eqx.tree_at(lambda e: e.upper_lashes, eye, tilted).obstacle_transmission(_grid())
    points, *_ = row.polylines(eye.lids)
    changed = np.argwhere(np.abs(np.asarray(a - b)) > 1e-6)
    assert changed.size > 0
    grid = _grid()
    y, x = (np.asarray(v) for v in grid.mesh_mm())
    xy = np.stack([x[tuple(changed.T)], y[tuple(changed.T)]], -1)
    root = np.asarray(points[2, 0])
    # Every changed pixel lies within the lash's length (plus its width) of its root.
    assert np.max(np.linalg.norm(xy - root, axis=-1)) <= 1.4 + 0.1


def test_config_round_trip_and_drawn_layout():
    """The layout is written into the row's table and read back; ``layout = "drawn"``
    freezes the key's draw."""
    eye = _eye()
    frozen = eqx.tree_at(lambda e: e.upper_lashes, eye, eye.upper_lashes.with_layout())
    table = eye_to_config(frozen)
    assert set(table["lashes_upper"]["layout"]) == set(LAYOUT_LEAVES)
    again = eye_from_config(table)
    np.testing.assert_array_equal(
        np.asarray(again.transmission(_grid())), np.asarray(frozen.transmission(_grid()))
    )
    assert "layout" not in eye_to_config(eye)["lashes_upper"]
    plain = eye_to_config(eye)
    plain["lashes_upper"]["layout"] = "drawn"
    drawn = eye_from_config(plain)
    np.testing.assert_allclose(
        np.asarray(drawn.upper_lashes.layout.angle_deg),
        np.asarray(eye.upper_lashes.drawn_layout().angle_deg),
        rtol=1e-6,
    )


@pytest.mark.parametrize(
    "change, text",
    [
        (lambda t: t.update(layout="random"), "'drawn'"),
        (lambda t: t["layout"].pop("angle_deg"), "angle_deg"),
        (lambda t: t["layout"].update(root_mm=[0.0, 1.0]), "one entry per lash"),
        (lambda t: t["layout"].update(extra=[1.0]), "extra"),
    ],
)
def test_bad_layout_tables_name_the_key(change, text):
    eye = _eye()
    table = eye_to_config(
        eqx.tree_at(lambda e: e.upper_lashes, eye, eye.upper_lashes.with_layout())
    )
    change(table["lashes_upper"])
    with pytest.raises(ConfigError, match=text):
        eye_from_config(table)


def test_layout_of_the_wrong_size_is_refused():
    row = _eye().upper_lashes
    layout = LashLayout(*(jnp.zeros(4) + 0.1 for _ in LAYOUT_LEAVES))
    with pytest.raises(ConfigError, match="n_max = 6"):
        row.with_layout(layout)


@functools.cache
def _leaf_problem():
    """(eye, loss, gradient) of the gradient tests, built once per module (float64).

    The loss is one jitted program shared by every leaf's differences, and autodiff's
    derivative in every per-lash value comes from one gradient program of the whole eye,
    instead of a forward and a gradient compilation per leaf.
    """
    with helpers.x64():
        grid = _grid()
        eye = _eye()
        eye = eqx.tree_at(lambda e: e.upper_lashes, eye, eye.upper_lashes.with_layout())
        eye = eye.with_stamp_windows(grid, headroom=1.5)
        weights = jnp.asarray(np.random.default_rng(1).uniform(size=(64, 64)))

        @eqx.filter_jit
        def loss(e):
            return jnp.sum(weights * e.transmission(grid))

        grads = eqx.filter_jit(eqx.filter_grad(loss))(eye)
        return eye, loss, grads


# A lash's length moves its tip along a curve: the coarser difference of 1e-4 is off by
# 7e-5 relative (truncation; it falls 16-fold at a quarter of the step), so a finer pair.
_STEP = {"length_mm": 2e-5}


@pytest.mark.parametrize("leaf", LAYOUT_LEAVES)
@pytest.mark.slow
def test_every_layout_leaf_gradient_converges_to_finite_differences_float64(leaf):
    """d/dx sum(w * transmission) of lash 2's and lash 3's per-lash values (both cross the
    pupil) by autodiff against central differences at two steps (1e-4 and 2.5e-5 of the
    value's scale; 2e-5 and 5e-6 for the length), converging, within rtol 1e-5 (float64)."""
    eye, loss, grads = _leaf_problem()
    with helpers.x64():

        def set_value(x, i):
            row = eye.upper_lashes
            arr = getattr(row.layout, leaf).at[i].set(x)
            return eqx.tree_at(lambda e: getattr(e.upper_lashes.layout, leaf), eye, arr)

        for i in (2, 3):
            x0 = float(getattr(eye.upper_lashes.layout, leaf)[i])
            scale = max(abs(x0), 0.1)
            ad, *_ = helpers.assert_grad_converges(
                lambda x, i=i: loss(set_value(x, i)),
                x0,
                _STEP.get(leaf, 1e-4) * scale,
                grad=float(getattr(grads.upper_lashes.layout, leaf)[i]),
                rtol=1e-5,
                err_msg=f"{leaf}[{i}]",
            )
            assert abs(ad) > 1e-3, f"{leaf}[{i}] barely moves the transmission (d = {ad:g})"


def test_prior_moments_are_those_the_key_draws_from():
    """Over 4000 lashes drawn by keys, the per-lash values scatter about the prior's means
    with its standard deviations: within 5 % (about 4 standard errors of an sd from 4000
    values), and the roots about their slots with ``jitter * spacing / sqrt(12)``."""
    with helpers.x64():
        row = Eyelashes(
            count=40.0, n_max=40, key=0, mean_angle_deg=3.0, angular_spread_deg=12.0,
            length_mm=2.5, length_spread=0.2, thickness_mm=0.06, thickness_spread=0.2,
            spacing_jitter=0.5, root_span_mm=8.0,
        )  # fmt: skip
        mean, sd = zip(*(prior_moments(row)[k] for k in LAYOUT_LEAVES), strict=True)
        draws = [
            eqx.tree_at(lambda r: r.key, row, jax.random.key(k)).drawn_layout() for k in range(100)
        ]
        for j, leaf in enumerate(LAYOUT_LEAVES[:4]):
            values = np.stack([np.asarray(getattr(d, leaf)) for d in draws])
            dev = (values - np.asarray(mean[j])) / np.asarray(sd[j])
            assert abs(dev.mean()) < 0.07, leaf
            assert abs(dev.std() - 1.0) < 0.05, (leaf, dev.std())
        curv = np.stack([np.asarray(d.curvature_per_mm) for d in draws])
        np.testing.assert_allclose(curv, float(row.curvature_per_mm))
        assert math.isclose(float(sd[0][0]), 0.5 * 8.0 / 40.0 / math.sqrt(12.0), rel_tol=1e-3)
