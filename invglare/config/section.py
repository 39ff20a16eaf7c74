"""The one strict reader of config tables: unknown keys and wrong types name the key."""

from __future__ import annotations

from typing import Any

import numpy as np

from invglare.errors import ConfigError

_TYPE_NAMES = {int: "an integer", float: "a number", str: "a string", bool: "true or false"}


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

    def numbers(self, key: str, default: Any = ..., shape: str = "") -> Any:
        """A number or a (nested) list of numbers, as a float array (`shape` names the form)."""
        value = self.get(key, (float, list), default)
        if value is default and default is not ...:
            return value
        try:
            return np.asarray(value, dtype=float)
        except (TypeError, ValueError) as err:
            raise ConfigError(
                f"{self.where}.{key} must be {shape or 'a number or a list of numbers'}, "
                f"got {value!r}"
            ) from err

    def choice(self, key: str, valid: tuple[str, ...], default: str) -> str:
        value = self.get(key, str, default)
        if value not in valid:
            raise ConfigError(f"{self.where}.{key} = {value!r} is not one of {', '.join(valid)}")
        return value

    def accept(self, keys) -> None:
        """Mark `keys` as read (by another reader this table hands them to)."""
        self._known.extend(keys)

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
