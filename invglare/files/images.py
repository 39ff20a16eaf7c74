"""Reading photos and HDR images in any supported format; writing PNGs; the sRGB curve.

`read_image` dispatches on the file extension:

| extension             | reader           | `data`                          | `display_encoded` |
|-----------------------|------------------|---------------------------------|-------------------|
| `.exr`                | `read_exr`       | linear float32 as stored        | `False`           |
| `.png`, `.jpg/.jpeg`  | imageio          | integer codes / max → [0, 1]    | `True`            |
| `.tif/.tiff`, integer | imageio          | integer codes / max → [0, 1]    | `True`            |
| `.tif/.tiff`, float   | imageio          | float32 as stored (HDR)         | `False`           |

Display-encoded data is *not* proportional to light: decode it (e.g. with
`decode_srgb`, or the camera's response curve) before comparing it with a
model. A 16-bit TIFF that is known to be linear can ignore the flag.

PNGs go through imageio's Pillow plugin. Pillow handles 16-bit *grey* PNGs
but reduces 16-bit colour (and grey + alpha) PNGs to 8 bits on reading and
cannot write them, so `read_image` refuses such files rather than return
degraded data, and `write_png` writes 16 bits for grey images only. Use EXR
(`write_exr`) or 16-bit TIFF for high-precision colour.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from invglare.errors import InputDataError
from invglare.files.atomic import atomic_write
from invglare.files.exr import read_exr, validate_pixels

__all__ = [
    "SUPPORTED_IMAGE_EXTENSIONS",
    "LoadedImage",
    "decode_srgb",
    "encode_srgb",
    "read_image",
    "write_png",
]

#: File extensions `read_image` understands (lower case; matching ignores case).
SUPPORTED_IMAGE_EXTENSIONS = (".exr", ".png", ".jpg", ".jpeg", ".tif", ".tiff")

_NAMES_BY_COUNT = {1: ("Y",), 2: ("Y", "A"), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}


@dataclass(frozen=True, eq=False)
class LoadedImage:
    """An image read by `read_image`.

    **Fields:**

    - `data`: float32, `(H, W)` for one channel, else `(H, W, C)`.
    - `channels`: names of the channels: `("Y",)`, `("Y", "A")`, `("R", "G", "B")`,
      `("R", "G", "B", "A")`, or as stored in an EXR.
    - `display_encoded`: `True` when `data` holds integer codes scaled to [0, 1]
      (gamma/sRGB-encoded, not proportional to radiance); `False` for linear
      float data (EXR, float TIFF).
    - `bit_depth`: bits per sample of an integer file (1, 8, 16, 32), `None` for float data.
    - `pixel_scale_deg`: degrees per pixel from an EXR header, else `None`.
    - `attrs`: extra EXR header attributes (empty for other formats).
    """

    data: np.ndarray
    channels: tuple[str, ...]
    display_encoded: bool
    bit_depth: int | None
    pixel_scale_deg: float | None = None
    attrs: dict[str, Any] = field(default_factory=dict)


# ----------------------------------------------------------------------------- sRGB


def encode_srgb(linear: Any) -> np.ndarray:
    """Apply the sRGB transfer function (IEC 61966-2-1): linear light → display code.

    **Arguments:**

    - `linear`: array of linear values, nominally in [0, 1] (1 = display white).

    **Returns:** the encoded values, same shape; float32 stays float32, other
    inputs become float64. Negative values follow the linear segment and values
    above 1 the power segment, so the function is monotone everywhere.

    ```python
    encode_srgb(0.0031308)  # ≈ 0.04045, where the two segments meet
    ```
    """
    x = np.asarray(linear)
    x = x if x.dtype.kind == "f" else x.astype(np.float64)
    # Clamp before the power so that negative inputs in the unused branch raise no warning.
    power = 1.055 * np.maximum(x, 0.0031308) ** (1 / 2.4) - 0.055
    return np.where(x <= 0.0031308, 12.92 * x, power).astype(x.dtype, copy=False)


def decode_srgb(encoded: Any) -> np.ndarray:
    """Invert `encode_srgb`: sRGB display code → linear light.

    **Arguments:**

    - `encoded`: array of sRGB-encoded values, nominally in [0, 1].

    **Returns:** linear values, same shape and dtype rules as `encode_srgb`.

    ```python
    decode_srgb(0.5)  # ≈ 0.21404
    ```
    """
    v = np.asarray(encoded)
    v = v if v.dtype.kind == "f" else v.astype(np.float64)
    power = ((np.maximum(v, 0.04045) + 0.055) / 1.055) ** 2.4
    return np.where(v <= 0.04045, v / 12.92, power).astype(v.dtype, copy=False)


# ----------------------------------------------------------------------------- PNG header

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _check_png_depth(path: Path) -> None:
    """Refuse a 16-bit colour or grey + alpha PNG, which Pillow would reduce to 8 bits."""
    with open(path, "rb") as f:
        head = f.read(26)
    # IHDR is always the first chunk: bit depth at byte 24, colour type at byte 25.
    if len(head) < 26 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        return  # not a PNG: the reader reports it
    if head[24] == 16 and head[25] != 0:  # colour type 0 = grey, read losslessly
        kind = {2: "RGB", 4: "grey + alpha", 6: "RGBA"}.get(head[25], f"type {head[25]}")
        raise InputDataError(
            f"{path}: 16-bit colour PNG ({kind}) is not supported: the PNG reader would "
            "reduce it to 8 bits; convert it to a 16-bit TIFF or an EXR"
        )


# ----------------------------------------------------------------------------- reading


def _read_raster(path: Path, ext: str) -> np.ndarray:
    if ext == ".png":
        _check_png_depth(path)
    import imageio.v3 as iio  # imported here: only needed for photos

    # Named plugins: otherwise imageio tries every plugin it knows on a bad file.
    # tifffile keeps 16-bit and float TIFFs intact but needs the optional
    # imagecodecs package for LZW/JPEG compression, which Pillow can decode.
    plugins = ("tifffile", "pillow") if ext in (".tif", ".tiff") else ("pillow",)
    problems = []
    for plugin in plugins:
        try:
            return np.asarray(iio.imread(path, plugin=plugin))
        except Exception as e:  # Pillow/tifffile raise many unrelated types for bad files
            problems.append(f"{plugin}: {e}")
    raise InputDataError(
        f"cannot read image {path}: not a valid {ext[1:].upper()} file or corrupt "
        f"({'; '.join(problems)})"
    )


def read_image(path: str | os.PathLike[str], *, allow_negative: bool = False) -> LoadedImage:
    """Read an image file as float32, choosing the reader by extension.

    **Arguments:**

    - `path`: an `.exr`, `.png`, `.jpg`/`.jpeg` or `.tif`/`.tiff` file.
    - `allow_negative`: accept negative values in float data (EXR, float TIFF).

    **Returns:** a `LoadedImage`. Integer files (8/16-bit PNG, JPEG, integer
    TIFF) are scaled to [0, 1] and flagged `display_encoded=True`; EXR and float
    TIFF data are returned as stored (linear) with `display_encoded=False`.

    **Raises:** `InputDataError` for an unsupported extension (listing the
    supported ones), a missing or unreadable file, an unsupported layout
    (CMYK JPEG, signed integers), or non-finite / negative float pixels.
    """
    src = Path(path)
    ext = src.suffix.lower()
    if ext not in SUPPORTED_IMAGE_EXTENSIONS:
        raise InputDataError(
            f"{src}: unsupported image type {ext or '(no extension)'!r}; "
            f"supported: {', '.join(SUPPORTED_IMAGE_EXTENSIONS)}"
        )
    if not src.exists():
        raise InputDataError(f"image file not found: {src}")
    if not src.is_file():
        raise InputDataError(f"{src} is not a file")
    if ext == ".exr":
        exr = read_exr(src, allow_negative=allow_negative)
        return LoadedImage(
            data=exr.data,
            channels=exr.channels,
            display_encoded=False,
            bit_depth=None,
            pixel_scale_deg=exr.pixel_scale_deg,
            attrs=exr.attrs,
        )

    arr = _read_raster(src, ext)
    if arr.ndim == 3 and arr.shape[-1] == 1:
        arr = arr[..., 0]
    if arr.size == 0:
        raise InputDataError(f"{src}: the file holds no pixels (empty or corrupt image)")
    if arr.ndim not in (2, 3):
        raise InputDataError(f"{src}: image has shape {arr.shape}; expected (H, W) or (H, W, C)")
    n = 1 if arr.ndim == 2 else arr.shape[-1]
    if ext in (".jpg", ".jpeg") and n == 4:
        raise InputDataError(f"{src}: CMYK JPEGs are not supported; convert it to RGB")

    if arr.dtype == np.bool_:  # 1-bit PNG/TIFF
        data, bit_depth, encoded = arr.astype(np.float32), 1, True
    elif arr.dtype.kind == "u":
        top = float(np.iinfo(arr.dtype).max)
        data = (arr.astype(np.float64) / top).astype(np.float32)
        bit_depth, encoded = arr.dtype.itemsize * 8, True
    elif arr.dtype.kind == "f":
        data, bit_depth, encoded = arr.astype(np.float32), None, False
    else:
        raise InputDataError(
            f"{src}: unsupported sample type {arr.dtype}; expected unsigned integers or floats"
        )
    if n > 4 and encoded:
        raise InputDataError(f"{src}: integer image with {n} channels; expected 1 to 4")
    names = _NAMES_BY_COUNT.get(n) or tuple(f"C{i}" for i in range(n))
    if not encoded:
        validate_pixels(src, data, names, allow_negative=allow_negative)
    return LoadedImage(
        data=np.ascontiguousarray(data),
        channels=names,
        display_encoded=encoded,
        bit_depth=bit_depth,
    )


# ----------------------------------------------------------------------------- writing


def write_png(path: str | os.PathLike[str], image: Any, *, bit_depth: int = 8) -> Path:
    """Write display-ready values in [0, 1] as an 8-bit (or 16-bit grey) PNG, atomically.

    **Arguments:**

    - `path`: destination; parent directories are created.
    - `image`: float (or bool) array, `(H, W)` grey, `(H, W, 2)` grey + alpha,
      `(H, W, 3)` RGB or `(H, W, 4)` RGBA. Values are written as given: encode
      linear data first (`encode_srgb`, or a tone map). Values outside [0, 1]
      are clipped.
    - `bit_depth`: 8 or 16 bits per sample; 16 only for a grey `(H, W)` image
      (Pillow cannot write 16-bit colour PNGs: use `write_exr` for linear data).

    **Returns:** the path written.

    **Raises:** `InputDataError` for NaN values, an integer array (ambiguous
    scale), a wrong shape, a bit depth other than 8 or 16, or a 16-bit request
    for an image with more than one channel.
    """
    target = Path(path)
    if bit_depth not in (8, 16):
        raise InputDataError(f"bit_depth must be 8 or 16; got {bit_depth!r}")
    arr = np.asarray(image)
    if arr.dtype.kind in "iu":
        raise InputDataError(
            f"write_png expects values in [0, 1]; got integer dtype {arr.dtype} "
            "(divide by 255 or 65535 first)"
        )
    if arr.dtype.kind not in "fb":
        raise InputDataError(f"write_png expects a float array; got dtype {arr.dtype}")
    if arr.ndim == 3 and arr.shape[-1] == 1:
        arr = arr[..., 0]
    if not (arr.ndim == 2 or (arr.ndim == 3 and arr.shape[-1] in (2, 3, 4))) or arr.size == 0:
        raise InputDataError(
            f"PNG image must have shape (H, W) or (H, W, C) with C in 2, 3, 4 and H, W > 0; "
            f"got {arr.shape}"
        )
    if bit_depth == 16 and arr.ndim == 3:
        raise InputDataError(
            f"cannot write {target}: 16-bit colour PNG is not supported (only 16-bit grey); "
            "write linear data with write_exr, or write an 8-bit PNG"
        )
    values = arr.astype(np.float64)
    nan = np.isnan(values)
    if nan.any():
        first = tuple(int(i) for i in np.unravel_index(int(np.argmax(nan)), nan.shape))
        raise InputDataError(
            f"cannot write {target}: the image has {int(nan.sum())} NaN value(s), first at "
            f"index {first}"
        )
    top = 255 if bit_depth == 8 else 65535
    # Clip before rounding and casting so out-of-range values (incl. ±inf) map to 0 / top
    # without overflow or cast warnings.
    codes = np.rint(np.clip(values, 0.0, 1.0) * top).astype(
        np.uint8 if bit_depth == 8 else np.uint16
    )
    import imageio.v3 as iio  # imported here: only needed for images

    # uint16 (H, W) becomes Pillow mode I;16, a 16-bit grey PNG.
    return atomic_write(
        target, lambda tmp: iio.imwrite(tmp, codes, plugin="pillow", extension=".png")
    )
