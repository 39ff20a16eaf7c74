"""Reading a frame and its depth buffer for the holographic eye (EXR Z channel or a file)."""

from __future__ import annotations

import numpy as np
import pytest

from invglare.errors import InputDataError
from invglare.files.depth_frames import read_frame_and_depth
from invglare.files.exr import write_exr


def test_z_channel_and_separate_depth_file(tmp_path):
    rgb = np.random.default_rng(0).random((6, 8, 3)).astype(np.float32)
    z = np.linspace(0.5, 20.0, 48, dtype=np.float32).reshape(6, 8)
    write_exr(tmp_path / "rgbz.exr", np.dstack([rgb, z]), pixel_scale_deg=0.01,
              channels=("R", "G", "B", "Z"))  # fmt: skip
    got = read_frame_and_depth(tmp_path / "rgbz.exr")
    np.testing.assert_array_equal(got.frame, rgb)
    np.testing.assert_array_equal(got.depth, z)
    assert "Z channel" in got.depth_source and got.pixel_scale_deg == pytest.approx(0.01)
    write_exr(tmp_path / "rgb.exr", rgb, pixel_scale_deg=0.01)
    write_exr(tmp_path / "depth.exr", 2 * z, pixel_scale_deg=0.01)  # a lone Y channel
    got = read_frame_and_depth(tmp_path / "rgb.exr", tmp_path / "depth.exr")
    np.testing.assert_array_equal(got.depth, 2 * z)
    assert read_frame_and_depth(tmp_path / "rgb.exr").depth is None


def test_depth_of_another_size_or_without_a_depth_channel_is_refused(tmp_path):
    rgb = np.ones((6, 8, 3), np.float32)
    write_exr(tmp_path / "rgb.exr", rgb, pixel_scale_deg=0.01)
    write_exr(tmp_path / "small.exr", np.ones((6, 7), np.float32), pixel_scale_deg=0.01)
    with pytest.raises(InputDataError, match=r"7 x 6 px but the frame .* is 8 x 6 px"):
        read_frame_and_depth(tmp_path / "rgb.exr", tmp_path / "small.exr")
    write_exr(tmp_path / "two.exr", np.ones((6, 8, 2), np.float32), pixel_scale_deg=0.01,
              channels=("A", "B"))  # fmt: skip
    with pytest.raises(InputDataError, match="no depth channel"):
        read_frame_and_depth(tmp_path / "rgb.exr", tmp_path / "two.exr")
    with pytest.raises(InputDataError, match="not found"):
        read_frame_and_depth(tmp_path / "missing.exr")
