"""TOML files: parsed into dicts, with every way a file can be unreadable turned into one line."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

from invglare.errors import ConfigError

#: The largest config file read (configs are a few KiB; tables of values a few MiB at most).
MAX_CONFIG_BYTES = 16 * 2**20


def load_toml(path: str | Path) -> dict[str, Any]:
    """Parse a TOML file; a missing, unreadable, non-text or malformed file is a ConfigError.

    **Raises:** :class:`~invglare.errors.ConfigError` naming the file and what is wrong with
    it: it does not exist, it is a folder or not a regular file, it is larger than
    ``MAX_CONFIG_BYTES``, it cannot be read, it is not UTF-8 text (a byte-order mark is
    allowed), it is empty, or it is not valid TOML.
    """
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"config {str(path)!r} is a folder, not a TOML file")
    if not path.exists():
        raise ConfigError(f"config file {str(path)!r} does not exist")
    if not path.is_file():  # a device or a pipe (/dev/zero) would be read without end
        raise ConfigError(f"config {str(path)!r} is not a regular file; a config is a TOML file")
    size = path.stat().st_size
    if size > MAX_CONFIG_BYTES:
        raise ConfigError(
            f"config file {str(path)!r} is {size / 2**20:.0f} MiB; a config is a TOML text "
            f"file of at most {MAX_CONFIG_BYTES // 2**20} MiB"
        )
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise ConfigError(f"config file {str(path)!r} cannot be read ({err.strerror})") from None
    try:
        text = raw.decode("utf-8-sig")  # a byte-order mark (Windows editors) is fine
    except UnicodeDecodeError as err:
        raise ConfigError(
            f"config file {str(path)!r} is not UTF-8 text (byte {err.start}); "
            "a config is a TOML text file"
        ) from None
    if not text.strip():
        raise ConfigError(f"config file {str(path)!r} is empty")
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{path}: not valid TOML ({err})") from err
