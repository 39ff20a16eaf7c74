"""Progressive refinement, area lights and batch spectral scaling (sec. 4.3-4.4)."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
import pytest

from invglare._core.grids import AngularGrid
from invglare.errors import ConfigError, InputDataError, PhysicsRangeError
from invglare.optics.quad import ProgressiveQuads, moving_shadow, progressive
from invglare.optics.quad.apertures import paper_grid, paper_raster
from invglare.optics.quad.arealight import area_light_image, serpentine
from invglare.optics.quad.spectral import (
    BatchPlan,
    batch_scaled_copies,
    batch_wavelengths_nm,
    full_scaled_copies,
)

N_AP, NPIX = 64, 96


def _output(grid, npix=NPIX, lam=550.0):
    return AngularGrid(npix, math.degrees(lam * 1e-6 / (2 * npix * float(grid.pitch_mm)) * 2))


@pytest.mark.parametrize("pixel_quads_up_to", [progressive.PIXEL_QUADS_UP_TO, 0])
@pytest.mark.parametrize("distance_mm", [None, 150.0])
def test_progressive_equals_full_evaluation_over_60_frames(
    distance_mm, pixel_quads_up_to, monkeypatch
):
    """The paper's benchmark animation (a circular shadow moving 5 px per frame) over the
    heptagon, far and near field, float32: every 10th frame and the last, the progressive
    image equals a full evaluation to 1e-5 of the peak (measured 6e-7 far, 2e-6 near on
    256 px; here 64 px), with the differences as pixels (the default here) and as the
    paper's quadtrees (forced). The difference quads are fewer than the full frame's."""
    monkeypatch.setattr(progressive, "PIXEL_QUADS_UP_TO", pixel_quads_up_to)
    grid = paper_grid(N_AP)
    aperture = paper_raster("heptagon", N_AP)
    frame = moving_shadow(aperture, 9.0, (2.0, 20.0), (1.0, 0.3))  # 5 px per frame at 320 px
    prog = ProgressiveQuads(grid, _output(grid), 550.0, distance_mm)
    worst = 0.0
    for t in range(60):
        raster = frame(t)
        psf = prog.psf(raster)
        if t % 10 == 9 or t == 59:
            ref = prog.full_psf(raster)
            worst = max(worst, float(np.max(np.abs(psf - ref)) / ref.max()))
    assert worst < 1e-5
    full_quads = prog.stats[0].quads
    assert np.mean([s.quads for s in prog.stats[1:]]) < full_quads
    assert [s.full for s in prog.stats] == [True] + [False] * 59


@pytest.mark.parametrize("pixel_quads_up_to", [progressive.PIXEL_QUADS_UP_TO, 0])
def test_difference_quads_add_up_to_the_difference(pixel_quads_up_to, monkeypatch):
    """Painting the quads of a signed difference (pixels, or the two quadtrees when forced)
    back onto the raster gives the difference exactly, at its place in the whole raster."""
    monkeypatch.setattr(progressive, "PIXEL_QUADS_UP_TO", pixel_quads_up_to)
    rng = np.random.default_rng(5)
    crop = np.where(rng.random((13, 21)) < 0.3, rng.normal(size=(13, 21)), 0.0)
    crop[4:12, 2:10] = 0.75  # a uniform block the quadtree merges
    origin = (7, 30)
    parts = progressive.difference_quads(crop, 0, origin)
    assert len(parts) == (1 if pixel_quads_up_to else 2)
    painted = np.zeros((40, 64))
    for x0, y0, w, h, amps in parts:
        for x, y, ww, hh, a in zip(x0, y0, w, h, amps, strict=True):
            painted[y : y + hh, x : x + ww] += a
    expected = np.zeros((40, 64))
    expected[7:20, 30:51] = crop
    np.testing.assert_allclose(painted, expected, rtol=0, atol=1e-12)


@pytest.mark.parametrize("near", [False, True])
def test_dense_and_gathered_inner_sums_give_the_same_update(near, monkeypatch):
    """A frame's quads (a random soft crop as pixels) summed into a dense matrix or
    gathered quad by quad (the choice forced both ways) give the same parity terms, far
    and near field, to 1e-5 of the largest (float32)."""
    from invglare.optics.quad import plan as plan_module

    rng = np.random.default_rng(3)
    crop = np.where(rng.random((20, 24)) < 0.5, rng.normal(size=(20, 24)), 0.0)
    parts = progressive.difference_quads(crop, 0, (30, 9))
    dyn, amps, _ = progressive.frame_plan(parts, (64, 64))
    step, alpha = np.float32(0.5), np.float32(0.01 if near else 0.0)
    terms = {}
    for per_quad in (0, 10**9):
        monkeypatch.setattr(plan_module, "DENSE_PER_QUAD", per_quad)
        assert dyn.dense_inner == bool(per_quad)
        args = (dyn, np.asarray(amps, np.float32), step, alpha, 64, near)
        terms[per_quad] = [np.asarray(t) for t in progressive._update(*args)]
    scale = max(float(np.max(np.abs(t))) for t in terms[0])
    assert scale > 0
    for dense, gathered in zip(terms[10**9], terms[0], strict=True):
        assert np.max(np.abs(dense - gathered)) < 1e-5 * scale


def test_moving_shadow_is_the_anti_aliased_disk_it_describes():
    """Each frame is the aperture times ``1 - clip(radius + 0.5 - r, 0, 1)`` over the whole
    raster (computed near the shadow only), also where the shadow leaves the raster."""
    aperture = np.random.default_rng(3).random((40, 28))
    frame = moving_shadow(aperture, 6.3, (-4.0, 9.2), (3.1, 1.4))
    yy, xx = np.mgrid[0:40, 0:28].astype(np.float64)
    for t in range(0, 16):
        r = np.hypot(xx - (-4.0 + 3.1 * t), yy - (9.2 + 1.4 * t))
        expected = aperture * (1.0 - np.clip(6.3 + 0.5 - r, 0.0, 1.0))
        np.testing.assert_allclose(frame(t), expected, rtol=0, atol=1e-15)


def test_progressive_handles_a_closed_aperture_and_refuses_bad_frames():
    grid = paper_grid(32)
    aperture = paper_raster("circle", 32)
    prog = ProgressiveQuads(grid, _output(grid, 32), 550.0)
    open_psf = prog.psf(aperture)
    assert np.all(prog.psf(np.zeros_like(aperture)) == 0.0)  # a blink: no light
    np.testing.assert_allclose(prog.psf(aperture), open_psf, atol=1e-7 * open_psf.max())
    with pytest.raises(InputDataError, match="32x32"):
        prog.psf(np.ones((16, 16)))
    with pytest.raises(PhysicsRangeError, match="distance_mm"):
        ProgressiveQuads(grid, _output(grid, 32), 550.0, 0.0)


def test_area_light_sums_each_samples_own_psf():
    """Without an occluder, the image is the point PSF spread over the samples (integer
    shifts, radiance weights); with one, each sample sees its own visible aperture, the
    image is darker, and a sample it hides entirely adds nothing."""
    grid = paper_grid(32)
    aperture = paper_raster("circle", 32)
    out = _output(grid, 48)
    offsets = np.array([[0, 0], [0, 1], [1, 0], [1, 1], [-2, 3]])
    radiance = np.array([1.0, 0.5, 0.5, 0.25, 0.1])
    order = serpentine(offsets)
    assert sorted(order.tolist()) == list(range(5))
    clear = area_light_image(ProgressiveQuads(grid, out, 550.0), aperture, offsets, radiance)
    point = ProgressiveQuads(grid, out, 550.0).full_psf(aperture)
    expected = np.zeros_like(point)
    for (dy, dx), w in zip(offsets, radiance, strict=True):
        expected += w * np.roll(np.roll(point, dy, axis=0), dx, axis=1)
    inner = np.s_[4:-4, 4:-4]  # away from what the rolls wrap around
    np.testing.assert_allclose(clear[inner], expected[inner], atol=1e-6 * point.max())
    occluder = np.zeros_like(aperture)
    occluder[:, :14] = 1.0  # a wall covering the left of the aperture
    shaded = area_light_image(
        ProgressiveQuads(grid, out, 550.0), aperture, offsets, radiance, occluder, 50.0
    )
    assert 0.2 * clear.sum() < shaded.sum() < 0.9 * clear.sum()
    with pytest.raises(InputDataError, match="integer"):
        area_light_image(ProgressiveQuads(grid, out, 550.0), aperture, offsets * 0.5, radiance)


@pytest.mark.slow
def test_batch_spectral_scaling_agrees_with_full_scaling():
    """60 geometric samples over 400-700 nm (reference 529.2 nm, the geometric mean): the
    4 + 15 resamplings of batch scaling against the 60 of full scaling, on a heptagon PSF:
    within 0.5 % of the peak (measured 0.29 %: the second interpolation), the same energy
    to 1 %."""
    from invglare.optics.quad import build_quadtree, detect_mirrors, make_plan, quad_far_field

    plan = BatchPlan.build(400.0, 700.0, 60)
    assert plan.inner.shape == (4,) and plan.outer.shape == (15,)
    np.testing.assert_allclose(np.sqrt(400.0 * 700.0), 529.150262, rtol=1e-9)
    raster = paper_raster("heptagon", 64)
    qplan = make_plan(build_quadtree(raster), *detect_mirrors(raster))
    psf = quad_far_field(qplan, jnp.asarray(raster, jnp.float32), 1 / 128, 128)
    batch = np.asarray(batch_scaled_copies(psf, plan))
    full = np.asarray(full_scaled_copies(psf, plan))
    assert np.max(np.abs(batch - full)) < 5e-3 * full.max()
    np.testing.assert_allclose(batch.sum(axis=(1, 2)), full.sum(axis=(1, 2)), rtol=1e-2)
    wl = batch_wavelengths_nm(400.0, 700.0, 8)
    np.testing.assert_allclose(wl[1:] / wl[:-1], (700 / 400) ** (1 / 7))
    with pytest.raises(ConfigError, match="multiple of 4"):
        batch_wavelengths_nm(400.0, 700.0, 30)
