"""File input and output at the edge of invglare: EXR, photos, PNG, atomic writes.

Everything here works on numpy arrays (JAX arrays are accepted on writing) and
raises `invglare.errors.InputDataError` for a missing, unreadable or bad file.
"""

from invglare.io.atomic import (
    atomic_path,
    atomic_write,
    dumps_json,
    write_json_atomic,
    write_text_atomic,
)
from invglare.io.exr import (
    CHANNELS_ATTR,
    CONFIG_ATTR,
    PIXEL_SCALE_ATTR,
    VERSION_ATTR,
    WAVELENGTHS_ATTR,
    ExrImage,
    read_exr,
    write_exr,
)
from invglare.io.images import (
    SUPPORTED_IMAGE_EXTENSIONS,
    LoadedImage,
    decode_srgb,
    encode_srgb,
    read_image,
    write_png,
)

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
    "read_exr",
    "read_image",
    "write_exr",
    "write_json_atomic",
    "write_png",
    "write_text_atomic",
]
