"""Self-describing OpenEXR files: PSFs and HDR images with their sampling in the header.

Layout of the files invglare writes (single part, scanline, ZIP compression):

- channels: `Y` for a monochrome image, `R`, `G`, `B` for colour, or any names
  given explicitly; float32 pixels, or half with `half=True`;
- `pixelScaleDeg` (float attribute): degrees per pixel, always present;
- `wavelengthsNm` (float-vector attribute): the wavelengths in nm a PSF was
  computed at, when given;
- `invglareConfig` (string attribute): the model configuration as JSON;
- `invglareVersion` (string attribute): the package version that wrote it;
- `invglareChannels` (string attribute): the channel names as a JSON list in
  the caller's order, because EXR itself stores channels sorted by name;
- any extra attributes passed by the caller (str, int, float, float vector).

EXR float attributes are 32-bit: numbers come back rounded to float32 and are
then given as the shortest decimal that rounds to the same float32, so a
pixel scale written as `0.01` reads back as exactly `0.01`.
"""

from __future__ import annotations

import json
import math
import os
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import OpenEXR

from invglare.errors import ConfigError, InputDataError, PhysicsRangeError
from invglare.files.atomic import atomic_write, dumps_json

__all__ = [
    "CHANNELS_ATTR",
    "CONFIG_ATTR",
    "PIXEL_SCALE_ATTR",
    "VERSION_ATTR",
    "WAVELENGTHS_ATTR",
    "ExrImage",
    "read_exr",
    "write_exr",
]

PIXEL_SCALE_ATTR = "pixelScaleDeg"
WAVELENGTHS_ATTR = "wavelengthsNm"
CONFIG_ATTR = "invglareConfig"
VERSION_ATTR = "invglareVersion"
CHANNELS_ATTR = "invglareChannels"

#: Header attributes that describe the file's layout rather than its content; they
#: are managed by OpenEXR and not reported in `ExrImage.attrs`.
_STRUCTURAL_ATTRS = frozenset(
    {
        "channels",
        "compression",
        "dataWindow",
        "displayWindow",
        "lineOrder",
        "pixelAspectRatio",
        "screenWindowCenter",
        "screenWindowWidth",
        "type",
        "tiles",
        "name",
        "version",
        "chunkCount",
    }
)
_OWN_ATTRS = frozenset(
    {PIXEL_SCALE_ATTR, WAVELENGTHS_ATTR, CONFIG_ATTR, VERSION_ATTR, CHANNELS_ATTR}
)

_HALF_MAX = float(np.finfo(np.float16).max)  # 65504
_FLOAT32_MAX = float(np.finfo(np.float32).max)
_INT32_MIN, _INT32_MAX = -(2**31), 2**31 - 1
_EXR_MAGIC = b"\x76\x2f\x31\x01"


@dataclass(frozen=True, eq=False)
class ExrImage:
    """Pixels and header of an EXR file, as returned by `read_exr`.

    **Fields:**

    - `data`: float32 pixels; `(H, W)` for a lone `Y` channel, otherwise
      `(H, W, C)` with the last axis in the order of `channels`.
    - `channels`: the channel names, e.g. `("Y",)` or `("R", "G", "B")`.
    - `pixel_scale_deg`: degrees per pixel (`pixelScaleDeg`), `None` if absent.
    - `wavelengths_nm`: the PSF's wavelengths in nm (`wavelengthsNm`), `None` if absent.
    - `config`: the model configuration stored by invglare, `None` if absent.
    - `attrs`: every other non-structural header attribute (including
      `invglareVersion` and standard ones such as `comment`).
    """

    data: np.ndarray
    channels: tuple[str, ...]
    pixel_scale_deg: float | None = None
    wavelengths_nm: tuple[float, ...] | None = None
    config: dict[str, Any] | None = None
    attrs: dict[str, Any] = field(default_factory=dict)


# ----------------------------------------------------------------------------- helpers


def _package_version() -> str:
    import invglare

    version = getattr(invglare, "__version__", None)
    if isinstance(version, str):
        return version
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version

    try:
        return dist_version("invglare")
    except PackageNotFoundError:
        return "unknown"


def _short_float(value: float) -> float:
    """The shortest decimal that rounds to the same float32, if `value` is a float32.

    Undoes the float32 storage of EXR attributes for values the user typed
    (0.01 is stored as 0.0099999998); doubles written by other tools pass unchanged.
    """
    f32 = np.float32(value)
    if math.isfinite(value) and float(f32) == value:
        # Not str(f32): numpy's legacy print mode (which colour-science switches on) rounds
        # it to 6 significant digits.
        return float(np.format_float_positional(f32, unique=True))
    return float(value)


def first_flagged(mask: np.ndarray, channels: Sequence[str] = ()) -> str:
    """Where the first flagged pixel of an ``(H, W)`` or ``(H, W, C)`` mask lies, for an
    error message: ``row r, column c``, and on three axes ``channel 'name'`` (the
    channel's index where `channels` does not name it)."""
    index = np.unravel_index(int(np.argmax(mask)), mask.shape)
    text = f"row {int(index[0])}, column {int(index[1])}"
    if len(index) == 3:
        c = int(index[2])
        text += f", channel {channels[c]!r}" if c < len(channels) else f", channel {c}"
    return text


def nonfinite_pixels(values: np.ndarray, channels: Sequence[str] = ()) -> tuple[int, str] | None:
    """How many pixels are NaN or Inf and ``(n NaN, m Inf), first at ...``, None where all
    are finite: the count and wording every reader's non-finite error shares."""
    bad = ~np.isfinite(values)
    if not bad.any():
        return None
    n_bad, n_nan = int(bad.sum()), int(np.isnan(values).sum())
    return n_bad, f"({n_nan} NaN, {n_bad - n_nan} Inf), first at {first_flagged(bad, channels)}"


def validate_pixels(
    path: Path, data: np.ndarray, channels: Sequence[str], *, allow_negative: bool
) -> None:
    """Raise `InputDataError` for non-finite or (unless allowed) negative pixels.

    `data` is `(H, W)` (one channel) or `(H, W, C)`; the message names the file,
    the channel, how many pixels are affected and where the first one is.
    """
    planes = data[..., None] if data.ndim == 2 else data
    for c, name in enumerate(channels):
        found = nonfinite_pixels(planes[..., c])
        if found is not None:
            n_bad, detail = found
            raise InputDataError(
                f"{path}: channel {name!r} has {n_bad} non-finite pixel(s) {detail}; "
                "expected finite values"
            )
    if allow_negative:
        return
    for c, name in enumerate(channels):
        plane = planes[..., c]
        neg = plane < 0
        if neg.any():
            raise InputDataError(
                f"{path}: channel {name!r} has {int(neg.sum())} negative pixel(s) "
                f"(minimum {float(plane.min()):g}), first at {first_flagged(neg)}; "
                "expected values >= 0 (pass allow_negative=True for signed data)"
            )


# ----------------------------------------------------------------------------- writing


def _planes_for_write(
    image: Any, channels: Sequence[str] | None
) -> tuple[np.ndarray, tuple[str, ...]]:
    """Validate the array's shape and dtype; return it as (H, W, C) floats and the names."""
    try:
        arr = np.asarray(image)
    except Exception as e:  # a ragged list or an object numpy cannot take
        raise InputDataError(f"EXR image cannot be converted to an array: {e}") from e
    if arr.dtype.kind not in "fiu":
        raise InputDataError(f"EXR pixels must be real numbers; got an array of dtype {arr.dtype}")
    if arr.ndim not in (2, 3):
        raise InputDataError(
            f"EXR image must have shape (H, W) or (H, W, C); got shape {arr.shape}"
        )
    if arr.size == 0:
        raise InputDataError(f"EXR image is empty: shape {arr.shape}")
    planes = arr[..., None] if arr.ndim == 2 else arr
    n = planes.shape[-1]
    if channels is None:
        if n == 1:
            names: tuple[str, ...] = ("Y",)
        elif n == 3:
            names = ("R", "G", "B")
        else:
            raise InputDataError(
                f"image of shape {arr.shape} has {n} channels; name them with channels=... "
                "(only 1 channel -> 'Y' and 3 channels -> 'R', 'G', 'B' are implied)"
            )
    else:
        if isinstance(channels, str):
            raise InputDataError(
                f"channels must be a sequence of names such as ('R', 'G', 'B'); got {channels!r}"
            )
        names = tuple(channels)
        if len(names) != n:
            raise InputDataError(
                f"channels names {len(names)} channel(s) {names} but the image of shape "
                f"{arr.shape} has {n}"
            )
        bad = [c for c in names if not isinstance(c, str) or not c]
        if bad:
            raise InputDataError(f"channel names must be non-empty strings; got {bad}")
        if len(set(names)) != len(names):
            raise InputDataError(f"channel names must be unique; got {names}")
    # Integers are widened for the range checks; floats are checked as they are.
    return (planes if planes.dtype.kind == "f" else planes.astype(np.float64)), names


def _check_write_values(path: Path, planes: np.ndarray, names: Sequence[str], half: bool) -> None:
    bad = ~np.isfinite(planes)
    if bad.any():
        raise InputDataError(
            f"cannot write {path}: the image has {int(bad.sum())} non-finite pixel value(s) "
            f"(NaN or Inf), first at {first_flagged(bad, names)}"
        )
    limit, kind = (_HALF_MAX, "half") if half else (_FLOAT32_MAX, "float32")
    over = np.abs(planes) > limit
    if over.any():
        raise InputDataError(
            f"cannot write {path}: {int(over.sum())} pixel value(s) exceed the largest {kind} "
            f"value {limit:g} (largest magnitude {float(np.abs(planes).max()):g}), first at "
            f"{first_flagged(over, names)}" + ("; write with half=False" if half else "")
        )


def _check_pixel_scale(pixel_scale_deg: Any) -> float:
    try:
        value = float(pixel_scale_deg)
    except (TypeError, ValueError) as e:
        raise PhysicsRangeError(
            f"pixel_scale_deg must be a number of degrees per pixel; got {pixel_scale_deg!r}"
        ) from e
    # The attribute is float32: a value that rounds to 0 or inf there is as bad as 0 or inf.
    stored = np.float32(value) if math.isfinite(value) else np.float32(np.inf)
    if not (math.isfinite(value) and value > 0 and np.isfinite(stored) and stored > 0):
        raise PhysicsRangeError(
            f"pixel_scale_deg must be a finite number > 0 (degrees per pixel); got {value!r}"
        )
    return value


def _check_wavelengths(wavelengths_nm: Any) -> list[float]:
    try:
        arr = np.asarray(wavelengths_nm, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise PhysicsRangeError(
            f"wavelengths_nm must be a sequence of numbers in nm; got {wavelengths_nm!r}"
        ) from e
    if arr.ndim == 0:
        arr = arr[None]
    if arr.ndim != 1 or arr.size == 0:
        raise PhysicsRangeError(
            f"wavelengths_nm must be a non-empty 1-D sequence in nm; got shape {arr.shape}"
        )
    # Imported here so that reading EXRs does not pull in JAX.
    from invglare._core.grids import WAVELENGTH_RANGE_NM

    lo, hi = WAVELENGTH_RANGE_NM
    bad = ~(np.isfinite(arr) & (arr >= lo) & (arr <= hi))
    if bad.any():
        raise PhysicsRangeError(
            f"wavelengths_nm must lie in [{lo:g}, {hi:g}] nm; got {arr[bad].tolist()} "
            "(a value far below 1 usually means metres or micrometres were given)"
        )
    return [float(w) for w in arr]


def _attr_value(name: Any, value: Any) -> Any:
    """Check one extra header attribute and convert it to what the binding stores faithfully."""
    if not isinstance(name, str) or not name:
        raise InputDataError(f"header attribute names must be non-empty strings; got {name!r}")
    if name in _STRUCTURAL_ATTRS or name in _OWN_ATTRS:
        raise InputDataError(
            f"header attribute {name!r} is managed by write_exr and cannot be set through attrs"
        )
    if isinstance(value, bool | np.bool_):
        raise InputDataError(f"header attribute {name!r} is a bool; store it as an int or a str")
    if isinstance(value, str):
        return value
    if isinstance(value, int | np.integer):
        # The binding silently wraps integers outside int32 (2**40 is stored as 0).
        if not _INT32_MIN <= int(value) <= _INT32_MAX:
            raise InputDataError(
                f"header attribute {name!r} = {value} does not fit a 32-bit int; store it as a str"
            )
        return int(value)
    if isinstance(value, float | np.floating):
        if not (math.isfinite(value) and abs(value) <= _FLOAT32_MAX):
            raise InputDataError(
                f"header attribute {name!r} = {value!r} is not a finite float32; store it as a str"
            )
        return float(value)
    if isinstance(value, Sequence | np.ndarray):
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            arr = None
        if (
            arr is not None
            and arr.ndim == 1
            and arr.size > 0
            and bool(np.all(np.isfinite(arr) & (np.abs(arr) <= _FLOAT32_MAX)))
        ):
            return [float(v) for v in arr]
        raise InputDataError(
            f"header attribute {name!r} = {value!r}: a sequence must be a non-empty list of "
            "finite numbers (stored as a float vector)"
        )
    raise InputDataError(
        f"header attribute {name!r} has type {type(value).__name__}; "
        "expected str, int, float or a list of floats"
    )


def write_exr(
    path: str | os.PathLike[str],
    image: Any,
    *,
    pixel_scale_deg: float,
    wavelengths_nm: Sequence[float] | np.ndarray | None = None,
    channels: Sequence[str] | None = None,
    config: Mapping[str, Any] | None = None,
    attrs: Mapping[str, Any] | None = None,
    half: bool = False,
) -> Path:
    """Write an image or PSF as a self-describing OpenEXR file, atomically.

    **Arguments:**

    - `path`: destination; parent directories are created.
    - `image`: numpy or JAX array, `(H, W)` → channel `Y`, `(H, W, 3)` → `R`, `G`,
      `B`, or `(H, W, C)` with `channels` naming each of the C channels.
    - `pixel_scale_deg`: angular size of one pixel in degrees, > 0 (`pixelScaleDeg`).
    - `wavelengths_nm`: wavelengths in nm the PSF was computed at (`wavelengthsNm`).
    - `channels`: channel names in the order of the last axis.
    - `config`: model configuration, stored as JSON (`invglareConfig`).
    - `attrs`: extra header attributes: str, int (32-bit), float or list of floats.
    - `half`: store 16-bit half floats instead of float32.

    **Returns:** the path written.

    **Raises:** `InputDataError` for a wrong shape, non-finite pixels, values
    too large for the pixel type or bad `attrs`; `PhysicsRangeError` for a bad
    pixel scale or wavelength; `ConfigError` if `config` is not JSON-serialisable.
    Nothing is written when validation fails.

    ```python
    write_exr("psf.exr", psf, pixel_scale_deg=0.01, wavelengths_nm=[450, 550, 650])
    ```
    """
    target = Path(path)
    planes, names = _planes_for_write(image, channels)
    _check_write_values(target, planes, names, half)

    header: dict[str, Any] = {
        "compression": OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
    }
    for key, value in (attrs or {}).items():
        header[key] = _attr_value(key, value)
    header[PIXEL_SCALE_ATTR] = _check_pixel_scale(pixel_scale_deg)
    if wavelengths_nm is not None:
        header[WAVELENGTHS_ATTR] = _check_wavelengths(wavelengths_nm)
    if config is not None:
        if not isinstance(config, Mapping):
            raise ConfigError(f"config must be a mapping (dict); got {type(config).__name__}")
        try:
            header[CONFIG_ATTR] = dumps_json(dict(config), indent=None)
        except (TypeError, ValueError) as e:
            raise ConfigError(f"config cannot be stored as JSON in {target}: {e}") from e
    header[VERSION_ATTR] = _package_version()
    header[CHANNELS_ATTR] = json.dumps(list(names))

    dtype = np.float16 if half else np.float32
    pixels = {
        name: np.ascontiguousarray(planes[..., i], dtype=dtype) for i, name in enumerate(names)
    }

    def _write(tmp: Path) -> None:
        try:
            with OpenEXR.File(header, pixels) as exr:
                exr.write(str(tmp))
        except (RuntimeError, ValueError, TypeError) as e:
            raise InputDataError(f"cannot write EXR file {target}: {e}") from e

    return atomic_write(target, _write)


# ----------------------------------------------------------------------------- reading


def _diagnose(path: Path) -> str:
    """Say why OpenEXR could not read `path`, by inspecting its (single-part) header.

    OpenEXR's own messages ("Unable to open ... for read") do not distinguish a
    foreign format from a truncated or empty-windowed file.
    """
    try:
        blob = path.read_bytes()
    except OSError as e:
        return f"the file cannot be read ({e})"
    if not blob:
        return "the file is empty (0 bytes)"
    if blob[:4] != _EXR_MAGIC:
        return f"not an OpenEXR file (it starts with {blob[:8]!r})"
    if len(blob) < 8:
        return "the file is truncated inside its header"
    flags = struct.unpack_from("<I", blob, 4)[0]
    if flags & 0x1000:  # multi-part: several headers, not parsed here
        return "corrupt or truncated multi-part OpenEXR file"
    pos = 8
    while True:
        end = blob.find(b"\0", pos)
        if end < 0:
            return "the file is truncated inside its header"
        name = blob[pos:end].decode("latin-1")
        pos = end + 1
        if not name:
            break
        end = blob.find(b"\0", pos)
        if end < 0 or end + 5 > len(blob):
            return "the file is truncated inside its header"
        kind = blob[pos:end].decode("latin-1")
        size = struct.unpack_from("<i", blob, end + 1)[0]
        pos = end + 5
        if size < 0 or pos + size > len(blob):
            return "the file is truncated inside its header"
        if name == "dataWindow" and kind == "box2i" and size == 16:
            xmin, ymin, xmax, ymax = struct.unpack_from("<4i", blob, pos)
            if xmax < xmin or ymax < ymin:
                return (
                    f"zero-size image: its dataWindow is ({xmin}, {ymin})-({xmax}, {ymax}), "
                    f"i.e. {max(xmax - xmin + 1, 0)} x {max(ymax - ymin + 1, 0)} pixels"
                )
        if name == "channels" and kind == "chlist" and size <= 1:
            return "the image has no channels"
        pos += size
    return "the header is valid but the pixel data is truncated or corrupt"


def _parse_float_attr(path: Path, name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float | np.number):
        raise InputDataError(f"{path}: header attribute {name} = {value!r} is not a number")
    return _short_float(float(value))


def _parse_pixel_scale(path: Path, value: Any) -> float:
    scale = _parse_float_attr(path, PIXEL_SCALE_ATTR, value)
    if not (math.isfinite(scale) and scale > 0):
        raise InputDataError(
            f"{path}: header attribute {PIXEL_SCALE_ATTR} = {scale!r}; "
            "expected a finite number of degrees per pixel > 0"
        )
    return scale


def _parse_wavelengths(path: Path, value: Any) -> tuple[float, ...]:
    try:
        if isinstance(value, str):  # written by another tool as "380,390,..."
            items = [float(s) for s in value.replace(";", ",").split(",") if s.strip()]
        else:
            items = [float(v) for v in np.asarray(value, dtype=np.float64).reshape(-1)]
    except (TypeError, ValueError) as e:
        raise InputDataError(
            f"{path}: header attribute {WAVELENGTHS_ATTR} = {value!r} is not a list of numbers"
        ) from e
    if not items or not all(math.isfinite(w) and w > 0 for w in items):
        raise InputDataError(
            f"{path}: header attribute {WAVELENGTHS_ATTR} = {value!r}; "
            "expected a non-empty list of positive wavelengths in nm"
        )
    return tuple(_short_float(w) for w in items)


def _parse_config(path: Path, value: Any) -> dict[str, Any]:
    try:
        config = json.loads(value) if isinstance(value, str) else None
    except json.JSONDecodeError as e:
        raise InputDataError(
            f"{path}: header attribute {CONFIG_ATTR} is not valid JSON ({e})"
        ) from e
    if not isinstance(config, dict):
        raise InputDataError(
            f"{path}: header attribute {CONFIG_ATTR} must hold a JSON object; got {value!r:.80}"
        )
    return config


def _attr_for_user(value: Any) -> Any:
    if isinstance(value, float):
        return _short_float(value)
    if isinstance(value, list) and all(isinstance(v, float) for v in value):
        return [_short_float(v) for v in value]
    return value


def _channel_order(names: Sequence[str], stored_order: Any) -> tuple[str, ...]:
    present = list(names)
    # The order invglare recorded wins, as long as it describes exactly these channels
    # (another tool may have added or dropped channels since).
    if isinstance(stored_order, str):
        try:
            recorded = json.loads(stored_order)
        except json.JSONDecodeError:
            recorded = None
        if (
            isinstance(recorded, list)
            and len(recorded) == len(present)
            and set(recorded) == set(present)
        ):
            return tuple(recorded)
    if {"R", "G", "B"} <= set(present):
        return ("R", "G", "B", *[n for n in present if n not in ("R", "G", "B")])
    return tuple(present)


def read_exr(
    path: str | os.PathLike[str],
    *,
    require_channels: Sequence[str] | None = None,
    allow_negative: bool = False,
) -> ExrImage:
    """Read an OpenEXR file (first part) with its invglare header attributes.

    **Arguments:**

    - `path`: the file.
    - `require_channels`: channel names that must be present, e.g. `("R", "G", "B")`.
    - `allow_negative`: accept negative pixels (signed data such as residuals).

    **Returns:** an `ExrImage`; `data` is float32, `(H, W)` for a lone `Y`
    channel, else `(H, W, C)` ordered as `channels` (R, G, B first when all
    three are present, or the order recorded by `write_exr`).

    **Raises:** `InputDataError`, naming the path and the problem, if the file is
    missing, not an EXR, corrupt or truncated, has a zero-size or subsampled
    or deep image, lacks a required channel (the message lists those present),
    holds NaN/Inf pixels or negative pixels (unless allowed), or has a
    malformed invglare header attribute.
    """
    src = Path(path)
    if not src.exists():
        raise InputDataError(f"EXR file not found: {src}")
    if not src.is_file():
        raise InputDataError(f"{src} is not a file (expected an OpenEXR image)")
    try:
        with OpenEXR.File(str(src), separate_channels=True) as exr:
            header = dict(exr.header())
            # Copy inside the block: the binding frees the pixels when the file closes.
            stored = {
                name: (
                    None if ch.pixels is None else np.array(ch.pixels),
                    int(ch.xSampling),
                    int(ch.ySampling),
                )
                for name, ch in exr.channels().items()
            }
    except Exception as e:  # the binding raises RuntimeError/ValueError for any bad file
        raise InputDataError(f"cannot read EXR file {src}: {_diagnose(src)} ({e})") from e

    if header.get("type") in (OpenEXR.deepscanline, OpenEXR.deeptile):
        raise InputDataError(f"{src}: deep EXR images are not supported; expected a flat image")
    if not stored:
        raise InputDataError(f"{src}: the image has no channels")
    for name, (pixels, xs, ys) in stored.items():
        if xs != 1 or ys != 1:
            raise InputDataError(
                f"{src}: channel {name!r} is subsampled ({xs} x {ys}); "
                "only full-resolution channels are supported"
            )
        if pixels is None or pixels.ndim != 2:
            raise InputDataError(f"{src}: channel {name!r} holds no readable pixel data")

    present = tuple(stored)
    missing = [c for c in (require_channels or ()) if c not in stored]
    if missing:
        raise InputDataError(
            f"{src}: missing required channel(s) {missing}; the file has {list(present)}"
        )

    order = _channel_order(present, header.get(CHANNELS_ATTR))
    shapes = {stored[n][0].shape for n in order}
    if len(shapes) != 1:
        raise InputDataError(f"{src}: channels have different sizes {sorted(shapes)}")
    (shape,) = shapes
    if 0 in shape:
        raise InputDataError(f"{src}: zero-size image ({shape[1]} x {shape[0]} pixels)")

    planes = [stored[n][0].astype(np.float32, copy=False) for n in order]
    data = planes[0] if order == ("Y",) else np.stack(planes, axis=-1)
    validate_pixels(src, data, order, allow_negative=allow_negative)

    pixel_scale = wavelengths = config = None
    attrs: dict[str, Any] = {}
    for key, value in header.items():
        if key == PIXEL_SCALE_ATTR:
            pixel_scale = _parse_pixel_scale(src, value)
        elif key == WAVELENGTHS_ATTR:
            wavelengths = _parse_wavelengths(src, value)
        elif key == CONFIG_ATTR:
            config = _parse_config(src, value)
        elif key not in _STRUCTURAL_ATTRS and key != CHANNELS_ATTR:
            attrs[key] = _attr_for_user(value)

    return ExrImage(
        data=np.ascontiguousarray(data),
        channels=order,
        pixel_scale_deg=pixel_scale,
        wavelengths_nm=wavelengths,
        config=config,
        attrs=attrs,
    )
