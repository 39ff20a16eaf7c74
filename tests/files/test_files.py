"""Tests of invglare.files: EXR and image round trips, header attributes, atomic writes, errors."""

from __future__ import annotations

import json
import re
import struct
import warnings
import zlib
from pathlib import Path

import imageio.v3 as iio
import jax.numpy as jnp
import numpy as np
import OpenEXR
import pytest
from PIL import Image

from invglare.errors import ConfigError, InputDataError, PhysicsRangeError
from invglare.files import (
    LoadedImage,
    atomic_path,
    atomic_write,
    decode_srgb,
    encode_srgb,
    read_exr,
    read_image,
    write_exr,
    write_json_atomic,
    write_png,
    write_text_atomic,
)
from invglare.files import exr as exr_module

RNG = np.random.default_rng(1234)


def _raw_exr(path: Path, channels: dict[str, np.ndarray], **header) -> Path:
    """Write an EXR with the bare binding, bypassing write_exr's validation."""
    hdr = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **header}
    with OpenEXR.File(hdr, channels) as f:
        f.write(str(path))
    return path


def _names(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


def _esc(path: Path) -> str:
    return re.escape(str(path))


# ----------------------------------------------------------------------------- EXR round trips

CASES = {
    "Y": ((9, 13), None, ("Y",)),
    "RGB": ((9, 13, 3), None, ("R", "G", "B")),
    # Deliberately not alphabetical: EXR sorts channels, the reader must restore this order.
    "named": ((9, 13, 4), ("w700", "w1000", "Z", "A"), ("w700", "w1000", "Z", "A")),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_exr_float_round_trip_is_exact(tmp_path, case):
    shape, channels, expected = CASES[case]
    # Values over many decades, as in a PSF, and exact zeros.
    image = (10.0 ** RNG.uniform(-8, 3, shape)).astype(np.float32)
    image[0, 0] = 0.0
    path = write_exr(tmp_path / "a.exr", image, pixel_scale_deg=0.02, channels=channels)
    got = read_exr(path)
    assert got.channels == expected
    assert got.data.dtype == np.float32
    assert got.data.shape == shape
    np.testing.assert_array_equal(got.data, image)


@pytest.mark.parametrize("case", sorted(CASES))
def test_exr_half_round_trip_within_half_precision(tmp_path, case):
    shape, channels, expected = CASES[case]
    image = RNG.uniform(0, 100, shape).astype(np.float32)
    path = write_exr(tmp_path / "h.exr", image, pixel_scale_deg=0.02, channels=channels, half=True)
    with OpenEXR.File(str(path), separate_channels=True) as f:
        assert {c.type() for c in f.channels().values()} == {OpenEXR.HALF}
    got = read_exr(path)
    assert got.channels == expected and got.data.dtype == np.float32
    # Exactly the nearest half, hence within half's relative precision 2**-11.
    np.testing.assert_array_equal(got.data, image.astype(np.float16).astype(np.float32))
    np.testing.assert_allclose(got.data, image, rtol=2.0**-11, atol=0)
    assert not np.array_equal(got.data, image)  # really stored as half


def test_exr_accepts_jax_arrays_and_single_channel_3d(tmp_path):
    image = jnp.linspace(0.0, 1.0, 30, dtype=jnp.float32).reshape(5, 6)
    got = read_exr(write_exr(tmp_path / "j.exr", image, pixel_scale_deg=1.0))
    np.testing.assert_array_equal(got.data, np.asarray(image))
    got = read_exr(write_exr(tmp_path / "k.exr", np.asarray(image)[..., None], pixel_scale_deg=1))
    assert got.channels == ("Y",) and got.data.shape == (5, 6)


def test_exr_header_attributes_round_trip(tmp_path):
    wavelengths = [380.0, 392.2, 404.4, 550.5, 779.9]
    config = {"model": {"kind": "kakimoto", "pupil": {"diameter_mm": 4.5}}, "n": [1, 2, 3]}
    attrs = {
        "comment": "glare of a 4.5 mm pupil",
        "exposureEv": 1.5,
        "frames": 12,
        "gains": [0.5, 0.1, 2.0],
        "note": "µm ≠ nm",
    }
    path = write_exr(
        tmp_path / "psf.exr",
        np.ones((4, 4, 3), np.float32),
        pixel_scale_deg=0.01,
        wavelengths_nm=np.array(wavelengths),
        config=config,
        attrs=attrs,
    )
    got = read_exr(path)
    # EXR float attributes are float32; the shortest float32 decimal gives the typed value back.
    assert got.pixel_scale_deg == 0.01
    assert got.wavelengths_nm == tuple(wavelengths)
    assert got.config == config
    for key, value in attrs.items():
        assert got.attrs[key] == value, key
    assert isinstance(got.attrs["invglareVersion"], str)
    # How they are stored in the file, for other tools.
    with OpenEXR.File(str(path), header_only=True) as f:
        header = dict(f.header())  # copied: the binding clears it on close
    assert isinstance(header["pixelScaleDeg"], float)
    np.testing.assert_array_equal(np.float32(header["wavelengthsNm"]), np.float32(wavelengths))
    assert json.loads(header["invglareConfig"]) == config


def test_exr_config_with_numpy_values_is_stored_as_plain_json(tmp_path):
    config = {"sigma": np.float32(0.5), "grid": np.arange(3), "path": tmp_path / "x.toml"}
    got = read_exr(
        write_exr(tmp_path / "c.exr", np.zeros((2, 2)), pixel_scale_deg=0.1, config=config)
    )
    assert got.config == {"sigma": 0.5, "grid": [0, 1, 2], "path": str(tmp_path / "x.toml")}
    assert got.wavelengths_nm is None


def test_exr_channel_order_of_foreign_files(tmp_path):
    h, w = 3, 4
    planes = {n: np.full((h, w), i, np.float32) for i, n in enumerate("ABGR")}
    got = read_exr(_raw_exr(tmp_path / "rgba.exr", planes))
    assert got.channels == ("R", "G", "B", "A")
    np.testing.assert_array_equal(got.data[0, 0], [3, 2, 1, 0])

    got = read_exr(_raw_exr(tmp_path / "y.exr", {"Y": np.ones((h, w), np.float32)}))
    assert got.channels == ("Y",) and got.data.shape == (h, w)
    assert got.pixel_scale_deg is None and got.config is None

    planes = {"Z": np.ones((h, w), np.float32), "Y": np.zeros((h, w), np.float32)}
    got = read_exr(_raw_exr(tmp_path / "yz.exr", planes))
    assert got.channels == ("Y", "Z") and got.data.shape == (h, w, 2)


def test_exr_wavelengths_written_as_text_by_other_tools(tmp_path):
    path = _raw_exr(
        tmp_path / "s.exr", {"Y": np.ones((2, 2), np.float32)}, wavelengthsNm="380,392.2, 550"
    )
    assert read_exr(path).wavelengths_nm == (380.0, 392.2, 550.0)


def test_exr_reads_uint_channels_as_float(tmp_path):
    ids = np.arange(12, dtype=np.uint32).reshape(3, 4)
    got = read_exr(_raw_exr(tmp_path / "u.exr", {"id": ids}))
    assert got.channels == ("id",) and got.data.dtype == np.float32
    np.testing.assert_array_equal(got.data[..., 0], ids)


def test_exr_negative_values_allowed_on_request(tmp_path):
    image = np.array([[-1.0, 2.0], [0.5, -0.25]], np.float32)
    path = write_exr(tmp_path / "r.exr", image, pixel_scale_deg=0.1)
    np.testing.assert_array_equal(read_exr(path, allow_negative=True).data, image)


# ----------------------------------------------------------------------------- EXR read errors


def test_read_exr_missing_file(tmp_path):
    path = tmp_path / "nope.exr"
    with pytest.raises(InputDataError, match=f"not found: {_esc(path)}"):
        read_exr(path)


def test_read_exr_directory(tmp_path):
    with pytest.raises(InputDataError, match=f"{_esc(tmp_path)} is not a file"):
        read_exr(tmp_path)


def test_read_exr_garbage_bytes(tmp_path):
    path = tmp_path / "garbage.exr"
    path.write_bytes(b"this is not an image\n" * 50)
    with pytest.raises(InputDataError, match=f"{_esc(path)}.*not an OpenEXR file"):
        read_exr(path)


def test_read_exr_empty_file(tmp_path):
    path = tmp_path / "empty.exr"
    path.write_bytes(b"")
    with pytest.raises(InputDataError, match=f"{_esc(path)}.*empty \\(0 bytes\\)"):
        read_exr(path)


@pytest.mark.parametrize("keep", ["header", "pixels"])
def test_read_exr_truncated(tmp_path, keep):
    full = write_exr(
        tmp_path / "full.exr", RNG.uniform(0, 1, (64, 80)).astype(np.float32), pixel_scale_deg=0.1
    ).read_bytes()
    path = tmp_path / "cut.exr"
    path.write_bytes(full[:40] if keep == "header" else full[: len(full) // 2])
    where = "inside its header" if keep == "header" else "pixel data is truncated"
    with pytest.raises(InputDataError, match=f"{_esc(path)}.*{where}"):
        read_exr(path)


def test_read_exr_zero_size_image(tmp_path):
    blob = write_exr(tmp_path / "one.exr", np.ones((1, 1)), pixel_scale_deg=0.1).read_bytes()
    key = b"dataWindow\0box2i\0" + struct.pack("<i", 16)
    at = blob.index(key) + len(key)
    path = tmp_path / "zero.exr"
    path.write_bytes(blob[:at] + struct.pack("<4i", 0, 0, -1, -1) + blob[at + 16 :])
    with pytest.raises(InputDataError, match=f"{_esc(path)}.*zero-size image.*0 x 0 pixels"):
        read_exr(path)


def test_read_exr_nan_and_inf_name_channel_and_count(tmp_path):
    g = np.ones((5, 6), np.float32)
    g[1, 2] = np.nan
    g[3, 4] = np.inf
    g[4, 0] = np.nan
    planes = {"R": np.ones((5, 6), np.float32), "G": g, "B": np.ones((5, 6), np.float32)}
    path = _raw_exr(tmp_path / "nan.exr", planes)
    with pytest.raises(
        InputDataError,
        match=f"{_esc(path)}: channel 'G' has 3 non-finite pixel\\(s\\) \\(2 NaN, 1 Inf\\), "
        "first at row 1, column 2",
    ):
        read_exr(path)
    # Non-finite values are refused even when negatives are allowed.
    with pytest.raises(InputDataError, match="non-finite"):
        read_exr(path, allow_negative=True)


def test_read_exr_negative_values(tmp_path):
    y = np.ones((4, 4), np.float32)
    y[2, 3] = -0.5
    y[3, 3] = -2.0
    path = _raw_exr(tmp_path / "neg.exr", {"Y": y})
    with pytest.raises(
        InputDataError,
        match=f"{_esc(path)}: channel 'Y' has 2 negative pixel\\(s\\) \\(minimum -2\\), "
        "first at row 2, column 3.*allow_negative=True",
    ):
        read_exr(path)


def test_read_exr_missing_required_channels_lists_present(tmp_path):
    path = write_exr(tmp_path / "y.exr", np.ones((3, 3)), pixel_scale_deg=0.1)
    with pytest.raises(
        InputDataError,
        match=f"{_esc(path)}: missing required channel\\(s\\) \\['R', 'B'\\]; "
        "the file has \\['Y'\\]",
    ):
        read_exr(path, require_channels=("R", "Y", "B"))
    assert read_exr(path, require_channels=["Y"]).channels == ("Y",)


def test_read_exr_bad_header_attributes(tmp_path):
    ones = {"Y": np.ones((2, 2), np.float32)}
    path = _raw_exr(tmp_path / "scale.exr", ones, pixelScaleDeg=-0.5)
    with pytest.raises(
        InputDataError, match=f"{_esc(path)}: header attribute pixelScaleDeg = -0.5"
    ):
        read_exr(path)
    path = _raw_exr(tmp_path / "cfg.exr", ones, invglareConfig="{not json")
    with pytest.raises(InputDataError, match=f"{_esc(path)}: header attribute invglareConfig"):
        read_exr(path)
    path = _raw_exr(tmp_path / "wl.exr", ones, wavelengthsNm="red,green")
    with pytest.raises(InputDataError, match=f"{_esc(path)}: header attribute wavelengthsNm"):
        read_exr(path)


# ----------------------------------------------------------------------------- EXR write errors


def _write_fails(tmp_path, error, match, image=None, **kwargs):
    kwargs.setdefault("pixel_scale_deg", 0.1)
    path = tmp_path / "out.exr"
    with pytest.raises(error, match=match):
        write_exr(path, np.ones((3, 4)) if image is None else image, **kwargs)
    assert _names(tmp_path) == []  # nothing written, not even a temporary file


def test_write_exr_non_finite_pixels(tmp_path):
    image = np.ones((4, 5, 3), np.float32)
    image[2, 1, 2] = np.nan
    image[3, 3, 0] = -np.inf
    _write_fails(
        tmp_path,
        InputDataError,
        "2 non-finite pixel value\\(s\\).*first at row 2, column 1, channel 'B'",
        image,
    )


@pytest.mark.parametrize(
    ("shape", "match"),
    [
        ((7,), "shape \\(H, W\\) or \\(H, W, C\\); got shape \\(7,\\)"),
        ((2, 3, 3, 1), "got shape \\(2, 3, 3, 1\\)"),
        ((0, 4), "empty: shape \\(0, 4\\)"),
        ((3, 4, 5), "has 5 channels; name them with channels="),
    ],
)
def test_write_exr_wrong_dims(tmp_path, shape, match):
    _write_fails(tmp_path, InputDataError, match, np.ones(shape))


def test_write_exr_bad_channel_names(tmp_path):
    _write_fails(
        tmp_path,
        InputDataError,
        "names 2 channel\\(s\\).*has 3",
        np.ones((2, 2, 3)),
        channels=("R", "G"),
    )
    _write_fails(
        tmp_path, InputDataError, "must be unique", np.ones((2, 2, 2)), channels=("X", "X")
    )
    _write_fails(tmp_path, InputDataError, "sequence of names", np.ones((2, 2, 3)), channels="RGB")


def test_write_exr_complex_pixels(tmp_path):
    _write_fails(tmp_path, InputDataError, "dtype complex128", np.ones((2, 2), complex))


@pytest.mark.parametrize("scale", [0.0, -0.01, float("nan"), float("inf"), 1e-60, "wide"])
def test_write_exr_bad_pixel_scale(tmp_path, scale):
    _write_fails(tmp_path, PhysicsRangeError, "pixel_scale_deg", pixel_scale_deg=scale)


def test_write_exr_wavelengths_in_metres(tmp_path):
    _write_fails(
        tmp_path, PhysicsRangeError, "wavelengths_nm.*5\\.5e-07", wavelengths_nm=[4.5e-7, 5.5e-7]
    )
    _write_fails(tmp_path, PhysicsRangeError, "non-empty", wavelengths_nm=[])


def test_write_exr_half_overflow(tmp_path):
    image = np.full((2, 3), 7e4, np.float32)
    _write_fails(
        tmp_path,
        InputDataError,
        "6 pixel value\\(s\\) exceed the largest half value 65504.*half=False",
        image,
        half=True,
    )


@pytest.mark.parametrize(
    ("attrs", "match"),
    [
        ({"big": 2**40}, "'big' = 1099511627776 does not fit a 32-bit int"),
        ({"flag": True}, "'flag' is a bool"),
        ({"obj": object()}, "'obj' has type object"),
        ({"v": []}, "'v'.*non-empty list"),
        ({"pixelScaleDeg": 3.0}, "'pixelScaleDeg' is managed by write_exr"),
        ({"channels": "x"}, "'channels' is managed by write_exr"),
        ({"huge": 1e300}, "'huge' = 1e\\+300 is not a finite float32"),
    ],
)
def test_write_exr_bad_attrs(tmp_path, attrs, match):
    _write_fails(tmp_path, InputDataError, match, attrs=attrs)


def test_write_exr_config_not_serialisable(tmp_path):
    _write_fails(
        tmp_path, ConfigError, "config cannot be stored as JSON.*object", config={"bad": object()}
    )


# ----------------------------------------------------------------------------- atomic writes


def test_atomic_write_failure_leaves_existing_file_and_no_temp(tmp_path):
    target = tmp_path / "result.json"
    target.write_bytes(b'{"old": true}\n')
    before = target.read_bytes()

    def broken(tmp: Path) -> None:
        tmp.write_bytes(b'{"new": tr')  # a partial file, then a crash
        raise RuntimeError("disk on fire")

    with pytest.raises(RuntimeError, match="disk on fire"):
        atomic_write(target, broken)
    assert target.read_bytes() == before
    assert _names(tmp_path) == ["result.json"]


def test_atomic_path_interrupted_leaves_no_temp(tmp_path):
    target = tmp_path / "x.txt"
    with pytest.raises(KeyboardInterrupt), atomic_path(target) as tmp:
        tmp.write_text("half")
        raise KeyboardInterrupt
    assert _names(tmp_path) == []


def test_atomic_write_replaces_and_creates_parents(tmp_path):
    target = tmp_path / "a" / "b" / "out.txt"
    write_text_atomic(target, "first")
    write_text_atomic(target, "second ✓")
    assert target.read_text(encoding="utf-8") == "second ✓"
    assert _names(target.parent) == ["out.txt"]
    # The temporary file keeps the target's extension (writers pick formats by it).
    seen = []
    atomic_write(tmp_path / "img.png", lambda tmp: (seen.append(tmp), tmp.write_bytes(b"x")))
    assert seen[0].suffix == ".png" and seen[0].parent == tmp_path


def test_atomic_write_requires_writer_to_create_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="did not create"):
        atomic_write(tmp_path / "x.bin", lambda tmp: None)
    assert _names(tmp_path) == []


def test_write_json_atomic_numpy_values(tmp_path):
    path = write_json_atomic(tmp_path / "p.json", {"x": np.float64(1.5), "a": np.arange(2)})
    assert json.loads(path.read_text()) == {"x": 1.5, "a": [0, 1]}
    with pytest.raises(TypeError, match="not JSON serialisable"):
        write_json_atomic(tmp_path / "q.json", {"x": object()})
    assert _names(tmp_path) == ["p.json"]


def test_write_exr_crash_mid_write_keeps_old_file(tmp_path, monkeypatch):
    target = write_exr(tmp_path / "psf.exr", np.ones((3, 3)), pixel_scale_deg=0.1)
    before = target.read_bytes()

    class CrashingFile:
        def __init__(self, *args, **kwargs):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def write(self, name):
            Path(name).write_bytes(before[:50])
            raise RuntimeError("simulated I/O failure")

    monkeypatch.setattr(exr_module.OpenEXR, "File", CrashingFile)
    with pytest.raises(InputDataError, match=f"cannot write EXR file {_esc(target)}.*simulated"):
        write_exr(target, np.zeros((5, 5)), pixel_scale_deg=0.2)
    assert target.read_bytes() == before
    assert _names(tmp_path) == ["psf.exr"]


def test_write_exr_invalid_data_keeps_old_file(tmp_path):
    target = write_exr(tmp_path / "psf.exr", np.ones((3, 3)), pixel_scale_deg=0.1)
    before = target.read_bytes()
    with pytest.raises(InputDataError):
        write_exr(target, np.full((3, 3), np.nan), pixel_scale_deg=0.1)
    assert target.read_bytes() == before
    assert _names(tmp_path) == ["psf.exr"]


# ----------------------------------------------------------------------------- PNG


def _png16(path: Path, codes: np.ndarray, colour_type: int) -> Path:
    """A minimal valid 16-bit PNG (no filters), of a kind Pillow cannot write."""
    h, w = codes.shape[:2]
    raw = b"".join(b"\0" + row.astype(">u2").tobytes() for row in codes)

    def chunk(kind: bytes, payload: bytes) -> bytes:
        crc = struct.pack(">I", zlib.crc32(kind + payload))
        return struct.pack(">I", len(payload)) + kind + payload + crc

    ihdr = struct.pack(">IIBBBBB", w, h, 16, colour_type, 0, 0, 0)
    parts = [chunk(b"IHDR", ihdr), chunk(b"IDAT", zlib.compress(raw)), chunk(b"IEND", b"")]
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + b"".join(parts))
    return path


@pytest.mark.parametrize("channels", [1, 2, 3, 4])
def test_png_round_trip_8bit(tmp_path, channels):
    shape = (7, 11) if channels == 1 else (7, 11, channels)
    codes = RNG.integers(0, 256, shape)
    codes.flat[:2] = [0, 255]
    path = write_png(tmp_path / "a.png", codes / 255)
    got = read_image(path)
    assert isinstance(got, LoadedImage)
    assert got.display_encoded and got.bit_depth == 8
    assert got.data.dtype == np.float32 and got.data.shape == shape
    assert len(got.channels) == channels
    np.testing.assert_array_equal(np.rint(got.data * 255), codes)
    np.testing.assert_allclose(got.data, codes / 255, atol=1e-7, rtol=0)
    np.testing.assert_array_equal(np.asarray(Image.open(path)), codes)


@pytest.mark.parametrize("shape", [(7, 11), (7, 11, 1)])
def test_png_round_trip_16bit_grey(tmp_path, shape):
    codes = RNG.integers(0, 65536, shape)
    codes.flat[:2] = [0, 65535]
    path = write_png(tmp_path / "g.png", codes / 65535, bit_depth=16)
    head = path.read_bytes()[:26]
    assert (head[24], head[25]) == (16, 0)  # really a 16-bit grey PNG
    got = read_image(path)
    assert got.display_encoded and got.bit_depth == 16 and got.channels == ("Y",)
    assert got.data.dtype == np.float32 and got.data.shape == (7, 11)
    np.testing.assert_array_equal(np.rint(got.data * 65535), codes.reshape(7, 11))
    np.testing.assert_allclose(got.data, codes.reshape(7, 11) / 65535, atol=1e-7, rtol=0)


def test_read_image_16bit_grey_png_from_pillow(tmp_path):
    # A smooth image makes Pillow's encoder choose predictive row filters.
    yy, xx = np.mgrid[0:40, 0:50]
    grey16 = (yy * 1500 + xx * 37).astype(np.uint16)
    Image.fromarray(grey16).save(tmp_path / "g16.png")
    got = read_image(tmp_path / "g16.png")
    assert got.bit_depth == 16 and got.channels == ("Y",)
    np.testing.assert_array_equal(np.rint(got.data * 65535), grey16)


@pytest.mark.parametrize("channels", [2, 3, 4])
def test_write_png_16bit_colour_is_refused(tmp_path, channels):
    path = tmp_path / "c.png"
    with pytest.raises(
        InputDataError,
        match=f"cannot write {_esc(path)}: 16-bit colour PNG is not supported.*write_exr.*8-bit",
    ):
        write_png(path, np.zeros((3, 4, channels)), bit_depth=16)
    assert _names(tmp_path) == []


@pytest.mark.parametrize(
    ("colour_type", "channels", "kind"), [(2, 3, "RGB"), (4, 2, "grey \\+ alpha"), (6, 4, "RGBA")]
)
def test_read_image_16bit_colour_png_is_refused(tmp_path, colour_type, channels, kind):
    codes = RNG.integers(0, 65536, (5, 6, channels)).astype(np.uint16)
    path = _png16(tmp_path / "c16.png", codes, colour_type)
    with pytest.raises(
        InputDataError,
        match=f"{_esc(path)}: 16-bit colour PNG \\({kind}\\) is not supported.*"
        "16-bit TIFF or an EXR",
    ):
        read_image(path)
    # The same writer's 16-bit grey file is read exactly, so the refusal is about colour only.
    grey = _png16(tmp_path / "g16.png", codes[..., :1], 0)
    np.testing.assert_array_equal(np.rint(read_image(grey).data * 65535), codes[..., 0])


def test_write_png_clips_without_warnings(tmp_path):
    image = np.array([[-0.5, 0.0, 0.5, 1.0, 1.5, np.inf, -np.inf]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        path = write_png(tmp_path / "c.png", image)
        got = read_image(path)
    np.testing.assert_array_equal(np.rint(got.data * 255), [[0, 0, 128, 255, 255, 255, 0]])


def test_write_png_errors(tmp_path):
    nan = np.zeros((3, 4, 3))
    nan[1, 2, 0] = np.nan
    with pytest.raises(InputDataError, match="1 NaN value\\(s\\), first at index \\(1, 2, 0\\)"):
        write_png(tmp_path / "n.png", nan)
    with pytest.raises(InputDataError, match="integer dtype uint8"):
        write_png(tmp_path / "i.png", np.zeros((2, 2), np.uint8))
    with pytest.raises(InputDataError, match="bit_depth must be 8 or 16; got 12"):
        write_png(tmp_path / "b.png", np.zeros((2, 2)), bit_depth=12)
    with pytest.raises(InputDataError, match="got \\(2, 2, 5\\)"):
        write_png(tmp_path / "s.png", np.zeros((2, 2, 5)))
    assert _names(tmp_path) == []


# ----------------------------------------------------------------------------- read_image


def test_read_image_exr_is_linear(tmp_path):
    image = RNG.uniform(0, 5, (4, 6, 3)).astype(np.float32)
    path = write_exr(tmp_path / "scene.exr", image, pixel_scale_deg=0.05, attrs={"k": "v"})
    got = read_image(path)
    assert not got.display_encoded and got.bit_depth is None
    assert got.pixel_scale_deg == 0.05 and got.attrs["k"] == "v"
    np.testing.assert_array_equal(got.data, image)


def test_read_image_tiff_integer_and_float(tmp_path):
    codes = RNG.integers(0, 65536, (5, 6, 3)).astype(np.uint16)
    iio.imwrite(tmp_path / "i.tif", codes)
    got = read_image(tmp_path / "i.tif")
    assert got.display_encoded and got.bit_depth == 16 and got.channels == ("R", "G", "B")
    np.testing.assert_array_equal(np.rint(got.data * 65535), codes)

    hdr = RNG.uniform(0, 1e4, (5, 6)).astype(np.float32)
    iio.imwrite(tmp_path / "f.TIFF", hdr)
    got = read_image(tmp_path / "f.TIFF")
    assert not got.display_encoded and got.bit_depth is None
    np.testing.assert_array_equal(got.data, hdr)

    hdr[2, 3] = np.nan
    iio.imwrite(tmp_path / "nan.tiff", hdr)
    with pytest.raises(InputDataError, match=re.escape("nan.tiff: channel 'Y' has 1 non-finite")):
        read_image(tmp_path / "nan.tiff")


def test_read_image_jpeg_and_one_bit_png(tmp_path):
    rgb = np.full((8, 8, 3), 200, np.uint8)
    iio.imwrite(tmp_path / "p.jpg", rgb, quality=95)
    got = read_image(tmp_path / "p.jpg")
    assert got.display_encoded and got.bit_depth == 8 and got.data.shape == (8, 8, 3)
    np.testing.assert_allclose(got.data, 200 / 255, atol=3 / 255)

    Image.fromarray(np.eye(4, dtype=bool)).save(tmp_path / "b.png")
    got = read_image(tmp_path / "b.png")
    assert got.bit_depth == 1
    np.testing.assert_array_equal(got.data, np.eye(4))


def test_read_image_errors(tmp_path):
    bmp = tmp_path / "photo.bmp"
    bmp.write_bytes(b"BM")
    with pytest.raises(
        InputDataError, match=f"{_esc(bmp)}: unsupported image type '.bmp'; supported: .exr, .png"
    ):
        read_image(bmp)
    with pytest.raises(InputDataError, match="unsupported image type '\\(no extension\\)'"):
        read_image(tmp_path / "README")
    with pytest.raises(InputDataError, match=f"not found: {_esc(tmp_path / 'x.png')}"):
        read_image(tmp_path / "x.png")
    # Seeded bytes, so that a failure can be rerun on the same file.
    rng = np.random.default_rng(20)
    garbage = tmp_path / "garbage.png"
    garbage.write_bytes(rng.bytes(256))
    with pytest.raises(InputDataError, match=f"cannot read image {_esc(garbage)}: not a valid PNG"):
        read_image(garbage)
    bad_tiff = tmp_path / "bad.tif"
    bad_tiff.write_bytes(b"II*\0" + rng.bytes(64))
    with pytest.raises(InputDataError, match=_esc(bad_tiff)):
        read_image(bad_tiff)
    Image.new("CMYK", (4, 4)).save(tmp_path / "cmyk.jpg")
    with pytest.raises(InputDataError, match=re.escape("cmyk.jpg: CMYK JPEGs are not supported")):
        read_image(tmp_path / "cmyk.jpg")


def test_read_image_truncated_16bit_png(tmp_path):
    blob = write_png(tmp_path / "full.png", RNG.uniform(0, 1, (40, 40)), bit_depth=16).read_bytes()
    path = tmp_path / "cut.png"
    path.write_bytes(blob[: len(blob) // 2])
    with pytest.raises(InputDataError, match=f"cannot read image {_esc(path)}.*truncated"):
        read_image(path)


# ----------------------------------------------------------------------------- sRGB


def test_srgb_known_values():
    assert encode_srgb(0.0031308) == pytest.approx(0.04045, abs=1e-6)
    assert encode_srgb(0.0) == 0.0
    assert encode_srgb(1.0) == pytest.approx(1.0, abs=1e-12)
    assert decode_srgb(0.5) == pytest.approx(0.21404, abs=1e-5)
    assert decode_srgb(0.04045) == pytest.approx(0.04045 / 12.92, rel=1e-12)
    assert decode_srgb(1.0) == pytest.approx(1.0, abs=1e-12)
    assert encode_srgb(0.18) == pytest.approx(0.46135, abs=1e-5)  # middle grey


def test_srgb_round_trip_and_dtypes():
    x = np.linspace(-0.1, 2.0, 2001)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # negative inputs must not hit the power branch
        y = encode_srgb(x)
        np.testing.assert_allclose(decode_srgb(y), x, rtol=1e-12, atol=1e-15)
    assert np.all(np.diff(y) > 0)
    x32 = x.astype(np.float32).reshape(3, 667, 1)
    assert encode_srgb(x32).dtype == np.float32 and encode_srgb(x32).shape == x32.shape
    assert decode_srgb(np.array([0, 255])).dtype == np.float64


def test_exr_float_attributes_keep_full_precision_in_legacy_print_mode(tmp_path):
    # colour-science switches numpy to legacy printing, which rounds str(float32) to 6 digits.
    old = np.get_printoptions()
    np.set_printoptions(legacy="1.13")
    try:
        write_exr(tmp_path / "a.exr", np.ones((4, 4), np.float32), pixel_scale_deg=0.015957769)
        assert read_exr(tmp_path / "a.exr").pixel_scale_deg == 0.015957769
    finally:
        np.set_printoptions(**old)
