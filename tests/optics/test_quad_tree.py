"""The quadtree: it represents the raster exactly, merges as the paper's fig. 2 says, and
refuses what it cannot build on."""

from __future__ import annotations

import logging

import jax.numpy as jnp
import numpy as np
import pytest
from helpers import x64

from invglare.errors import InputDataError, PhysicsRangeError
from invglare.optics.quad import build_quadtree


def _rebuild(layout, raster) -> np.ndarray:
    """Sum the layout's signed quads back into a raster (numpy, the reference)."""
    with x64():
        amps = np.asarray(layout.amplitudes(layout.intensities(jnp.asarray(raster))))
    out = np.zeros(layout.shape)
    for k in range(layout.n_quads):
        y0, x0, h, w = layout.y0[k], layout.x0[k], layout.h[k], layout.w[k]
        out[y0 : y0 + h, x0 : x0 + w] += amps[k]
    return out


def _blocky(rng, rows, cols):
    """Random blocks of 4 px with scattered grey pixels: every merge rule is exercised."""
    coarse = (rng.random((rows // 4 + 1, cols // 4 + 1)) < 0.5).astype(float)
    raster = np.kron(coarse, np.ones((4, 4)))[:rows, :cols]
    raster[rng.random((rows, cols)) < 0.05] = 0.5
    raster[rng.random((rows, cols)) < 0.03] = rng.random()
    return raster


@pytest.mark.parametrize("band", [None, 0, 2])
def test_quads_add_up_to_the_raster_exactly(band):
    rng = np.random.default_rng(3)
    for shape in ((32, 32), (37, 37), (40, 29)):
        raster = _blocky(rng, *shape)
        layout = build_quadtree(raster, band=band)
        np.testing.assert_allclose(_rebuild(layout, raster), raster, atol=1e-12)
        with x64():
            assert float(layout.departure(jnp.asarray(raster))) < 1e-12


def test_merges_negative_and_non_square_quads_as_in_fig_2():
    """Three of four open (fig. 2a): one parent quad and a negative one; two adjacent open
    (fig. 2b): one 2:1 quad; one open: that quad alone."""
    three = np.array([[1.0, 1.0], [1.0, 0.0]])
    layout = build_quadtree(three)
    assert layout.counts() == {"quads": 2, "negative": 1, "non_square": 0, "sizes": 2}
    two = np.array([[1.0, 1.0], [0.0, 0.0]])
    layout = build_quadtree(two)
    assert (layout.n_quads, int(layout.w[0]), int(layout.h[0])) == (1, 2, 1)
    diagonal = np.array([[1.0, 0.0], [0.0, 1.0]])
    assert build_quadtree(diagonal).counts()["quads"] == 2


def test_soft_edges_are_single_quads_with_their_own_intensity():
    """A fractional pixel is its own group (its gradient is that pixel's transform); a
    pixel within the band of one is too; the fully open ones share one intensity."""
    raster = np.zeros((8, 8))
    raster[2:6, 2:6] = 1.0
    raster[2, 3] = 0.4
    tight = build_quadtree(raster, band=0)
    banded = build_quadtree(raster, band=1)
    assert tight.n_unique == 1 and banded.n_unique > 1
    assert tight.n_groups == 2  # the grey pixel, the value 1


def test_base_level_one_represents_the_2x2_means():
    """The paper's half-size start: the quads stand for the 2x2 cell means."""
    rng = np.random.default_rng(5)
    raster = _blocky(rng, 32, 32)
    layout = build_quadtree(raster, base_level=1)
    means = raster.reshape(16, 2, 16, 2).mean(axis=(1, 3))
    np.testing.assert_allclose(
        _rebuild(layout, raster), np.kron(means, np.ones((2, 2))), atol=1e-12
    )


def test_padding_is_said_and_changes_nothing(caplog):
    """A 40 x 29 raster is padded to 64 x 64 with zeros: the note and the log say so, and
    the quads still add up to the raster in its own coordinates."""
    raster = _blocky(np.random.default_rng(1), 40, 29)
    with caplog.at_level(logging.INFO, logger="invglare"):
        layout = build_quadtree(raster)
    assert "40x29 raster is not square" in layout.note and "64x64" in layout.note
    assert "padded" in caplog.text
    np.testing.assert_allclose(_rebuild(layout, raster), raster, atol=1e-12)
    assert build_quadtree(np.ones((16, 16))).note == ""


@pytest.mark.parametrize(
    ("raster", "kwargs", "error", "match"),
    [
        (np.zeros((16, 16)), {}, InputDataError, "empty"),
        (np.ones(16), {}, InputDataError, "2-D"),
        (np.full((8, 8), np.nan), {}, InputDataError, "non-finite"),
        (np.ones((8, 8)) * (1 + 1j), {}, InputDataError, "real raster"),
        (np.ones((8, 8)), {"base_level": -1}, PhysicsRangeError, "base_level"),
        (np.ones((8, 8)), {"base_level": 4}, PhysicsRangeError, "larger than"),
        (np.ones((8, 8)), {"band": 1.5}, PhysicsRangeError, "band"),
    ],
)
def test_bad_rasters_are_refused_with_the_reason(raster, kwargs, error, match):
    with pytest.raises(error, match=match):
        build_quadtree(raster, **kwargs)


def test_a_layout_refuses_a_raster_of_another_size():
    layout = build_quadtree(np.ones((8, 8)))
    with pytest.raises(InputDataError, match="8x8 raster"):
        layout.intensities(jnp.ones((16, 16)))
