"""Files, the bottom of invglare's I/O: EXR, photos, PNG, TOML, atomic writes.

Every tier may import from here; nothing here imports from another tier (only
:mod:`invglare.errors` and :mod:`invglare._core`).

Everything here works on numpy arrays (JAX arrays are accepted on writing) and
raises `invglare.errors.InputDataError` for a missing, unreadable or bad file.
"""

from invglare.files.atomic import (
    atomic_path,
    atomic_write,
    dumps_json,
    write_json_atomic,
    write_text_atomic,
)
from invglare.files.exr import (
    CHANNELS_ATTR,
    CONFIG_ATTR,
    PIXEL_SCALE_ATTR,
    VERSION_ATTR,
    WAVELENGTHS_ATTR,
    ExrImage,
    read_exr,
    write_exr,
)
from invglare.files.images import (
    SUPPORTED_IMAGE_EXTENSIONS,
    LoadedImage,
    decode_srgb,
    encode_srgb,
    read_image,
    write_png,
)
from invglare.files.toml import load_toml

__all__ = [
    "CHANNELS_ATTR",
    "CONFIG_ATTR",
    "PIXEL_SCALE_ATTR",
    "SUPPORTED_IMAGE_EXTENSIONS",
    "VERSION_ATTR",
    "WAVELENGTHS_ATTR",
    "ExrImage",
    "LoadedImage",
    "atomic_path",
    "atomic_write",
    "decode_srgb",
    "dumps_json",
    "encode_srgb",
    "load_toml",
    "read_exr",
    "read_image",
    "write_exr",
    "write_json_atomic",
    "write_png",
    "write_text_atomic",
]
