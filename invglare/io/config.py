"""Strict TOML configs: unknown keys and wrong types are errors that name the key."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

from invglare.errors import ConfigError

_TYPE_NAMES = {int: "an integer", float: "a number", str: "a string", bool: "true or false"}


def load_toml(path: str | Path) -> dict[str, Any]:
    """Parse a TOML file, turning missing files and syntax errors into :class:`ConfigError`."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file {str(path)!r} does not exist")
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{path}: not valid TOML ({err})") from err


class Section:
    """A config table read key by key; :meth:`finish` rejects the keys nobody asked for.

    Typical use::

        sec = Section(cfg.get("output", {}), "output")
        npix = sec.get("npix", int, 512)
        sec.finish()
    """

    def __init__(self, table: Any, where: str):
        if not isinstance(table, dict):
            raise ConfigError(f"[{where}] must be a table, got {table!r}")
        self.table = table
        self.where = where
        self._known: list[str] = []

    def get(self, key: str, kind: type | tuple[type, ...], default: Any = ..., required=False):
        """Value of `key` checked against `kind` (int is accepted where float is asked)."""
        self._known.append(key)
        if key not in self.table:
            if required or default is ...:
                raise ConfigError(f"[{self.where}] needs the key {key!r}")
            return default
        value = self.table[key]
        kinds = kind if isinstance(kind, tuple) else (kind,)
        ok = any(
            isinstance(value, k) and not (k in (int, float) and isinstance(value, bool))
            for k in kinds
        ) or (float in kinds and isinstance(value, int) and not isinstance(value, bool))
        if not ok:
            expected = " or ".join(_TYPE_NAMES.get(k, k.__name__) for k in kinds)
            raise ConfigError(f"{self.where}.{key} must be {expected}, got {value!r}")
        if float in kinds and isinstance(value, int) and int not in kinds:
            value = float(value)
        return value

    def choice(self, key: str, valid: tuple[str, ...], default: str) -> str:
        value = self.get(key, str, default)
        if value not in valid:
            raise ConfigError(f"{self.where}.{key} = {value!r} is not one of {', '.join(valid)}")
        return value

    def finish(self) -> None:
        unknown = [k for k in self.table if k not in self._known]
        if unknown:
            raise ConfigError(
                f"[{self.where}] has unknown key {unknown[0]!r}; valid keys: "
                f"{', '.join(self._known)}"
            )


def check_sections(config: dict[str, Any], valid: tuple[str, ...], source: str) -> None:
    """Reject top-level tables that no command reads (usually a typo)."""
    for key in config:
        if key not in valid:
            raise ConfigError(
                f"{source}: unknown section [{key}]; valid sections: {', '.join(valid)}"
            )
