"""Point sources of the holographic eye: frustum, depth decoding, layouts, input checks."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
import pytest

from invglare.errors import ConfigError, InputDataError, PhysicsRangeError
from invglare.optics.holographic import (
    Frustum,
    HoloSampling,
    bins_to_image,
    decode_depth,
    image_to_bins,
    reproject,
)
from invglare.optics.holographic.sources import (
    check_depth_buffer,
    check_frame,
    crop_frame,
    directions,
    place_frame,
    source_amplitudes,
)


def test_normalised_depth_decodes_to_near_far_and_the_hyperbola():
    fr = Frustum(near_mm=100.0, far_mm=10000.0, depth_encoding="normalised")
    z = np.asarray(decode_depth(jnp.asarray([0.0, 1.0, 0.5]), fr))
    # Direct3D: d = f (z - n) / (z (f - n)); at d = 1/2, z = 2 n f / (f + n).
    np.testing.assert_allclose(z, [100.0, 10000.0, 2 * 100 * 10000 / 10100], rtol=1e-6)
    lin = Frustum(near_mm=100.0, far_mm=300.0, depth_encoding="linear01")
    assert float(decode_depth(0.25, lin)) == pytest.approx(150.0)
    assert float(decode_depth(2.0, Frustum())) == pytest.approx(2000.0)  # metres


def test_ray_distance_becomes_planar_depth():
    ty, tx = directions(8, 0.01)
    fr = Frustum(depth_encoding="distance", depth_unit_mm=1.0)
    z = decode_depth(jnp.full((8, 8), 1000.0), fr, (ty, tx))
    p = reproject(z, 0.01)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(p), axis=-1), 1000.0, rtol=1e-6)
    # Row 0 looks up, the last column right; the centre pixel down the axis.
    assert float(p[0, 4, 1]) > 0 and float(p[4, 7, 0]) > 0
    np.testing.assert_allclose(np.asarray(p[4, 4]), [0.0, 0.0, 1000.0], atol=1e-9)
    with pytest.raises(ConfigError, match="directions"):
        decode_depth(1.0, fr)


def test_frustum_rejects_bad_settings():
    with pytest.raises(ConfigError, match="depth_encoding"):
        Frustum(depth_encoding="log")
    with pytest.raises(ConfigError, match="near_mm and far_mm"):
        Frustum(depth_encoding="normalised", near_mm=100.0)
    with pytest.raises(PhysicsRangeError, match="below far_mm"):
        Frustum(near_mm=500.0, far_mm=100.0)
    with pytest.raises(PhysicsRangeError, match="fov_x_deg"):
        Frustum(fov_x_deg=190.0)
    fr = Frustum(fov_x_deg=2.0)
    assert fr.pixel_scale_rad(100) == pytest.approx(2 * math.tan(math.radians(1.0)) / 100)


def test_bin_layout_is_a_mirror_and_its_inverse():
    rng = np.random.default_rng(0)
    for n in (8, 16):
        x = jnp.asarray(rng.random((2, n, n)))
        np.testing.assert_array_equal(np.asarray(bins_to_image(image_to_bins(x))), np.asarray(x))
        # The centre pixel is bin 0; one pixel to the right (tan_x > 0) sends light to -x.
        img = np.zeros((n, n))
        img[n // 2, n // 2 + 1] = 1.0
        b = np.asarray(image_to_bins(jnp.asarray(img)))
        assert b[0, n - 1] == 1.0
        img = np.zeros((n, n))
        img[n // 2 - 1, n // 2] = 1.0  # one pixel up (tan_y > 0) travels down: -y, row -1
        assert np.asarray(image_to_bins(jnp.asarray(img)))[n - 1, 0] == 1.0


def test_place_and_crop_frame_with_an_input_step():
    frame = jnp.arange(12.0).reshape(1, 3, 4) + 1
    placed = place_frame(frame, 16, step=3)
    assert float(placed.sum()) == float(frame.sum())
    # Pixel (0, 0) lands at (r0 + 1, c0 + 1) with r0 = (16 - 9) // 2 = 3, c0 = (16 - 12) // 2 = 2.
    assert float(placed[0, 4, 3]) == 1.0
    crop = crop_frame(placed, (3, 4), step=3)
    assert crop.shape == (1, 9, 12)
    np.testing.assert_array_equal(np.asarray(crop[0, 1::3, 1::3]), np.asarray(frame[0]))
    with pytest.raises(InputDataError, match="needs a grid"):
        place_frame(frame, 8, step=3)
    np.testing.assert_allclose(np.asarray(source_amplitudes(frame, 2)), 2 * np.sqrt(frame))


def test_frame_and_depth_checks_name_the_problem():
    frame = np.ones((4, 5, 3))
    fr = Frustum()
    with pytest.raises(InputDataError, match=r"shape \(4, 4\) but the frame is \(4, 5\)"):
        check_depth_buffer(np.ones((4, 4)), frame.shape, fr)
    bad = np.ones((4, 5))
    bad[1, 2] = np.nan
    with pytest.raises(InputDataError, match=r"non-finite value nan at \(1, 2\)"):
        check_depth_buffer(bad, frame.shape, fr)
    bad[1, 2] = -3.0
    with pytest.raises(InputDataError, match=r"depth -3 at \(1, 2\)"):
        check_depth_buffer(bad, frame.shape, fr)
    norm = Frustum(near_mm=10.0, far_mm=100.0, depth_encoding="normalised")
    with pytest.raises(InputDataError, match="outside"):
        check_depth_buffer(np.full((4, 5), 1.5), frame.shape, norm)
    check_depth_buffer(np.full((4, 5, 1), 0.5), frame.shape, norm)  # a Z channel of shape (H, W, 1)
    with pytest.raises(InputDataError, match="negative"):
        check_frame(-frame)
    inf = frame.copy()
    inf[0, 0, 1] = np.inf
    with pytest.raises(InputDataError, match="non-finite"):
        check_frame(inf)
    with pytest.raises(InputDataError, match="shape"):
        check_frame(np.ones(5))


def test_sampling_ties_pitch_window_and_pixel_scale():
    s = HoloSampling.from_window(512, 8.0, (640.0, 550.0, 460.0))
    assert s.pixel_scale_rad == pytest.approx(460e-6 / 8.0)
    assert s.pitch_mm(460.0) == pytest.approx(8.0 / 512)
    assert s.window_mm(640.0) == pytest.approx(8.0 * 640 / 460)
    assert s.half_field_rad == pytest.approx(256 * 460e-6 / 8.0)
    with pytest.raises(ConfigError, match="even"):
        HoloSampling(63, 1e-4, (550.0,))
    with pytest.raises(PhysicsRangeError, match="micrometres"):
        HoloSampling(64, 1e-4, (0.55,))
