"""The one strict reader of config tables: unknown keys and wrong types name the key."""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import numpy as np

from invglare.errors import ConfigError, InputDataError, PhysicsRangeError, prefixed
from invglare.files.toml import load_toml

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
    def only(self, *keys: str) -> None:
        """Reject at once every key of the table that is not one of `keys`.

        A reader calls it before reading, so that a misspelt key is named as unknown
        instead of the key it misspells being reported missing; :meth:`finish` still
        runs at the end.

        **Raises:** `ConfigError` naming the first unknown key and listing `keys`.
        """
        unknown = [k for k in self.table if k not in keys]
        if unknown:
            raise ConfigError(
                f"[{self.where}] has unknown key {unknown[0]!r}; valid keys: {', '.join(keys)}"
            )

    def section(self, key: str, required: bool = False) -> Section | None:
        """The sub-table `key` as a Section named ``where.key``; None when it is absent.

        **Raises:** `ConfigError` when it is absent and `required`, or not a table.
        """
        present, value = self._raw(key, ... if required else None)
        return Section(value, f"{self.where}.{key}") if present else None

    def sections(self, key: str) -> list[Section]:
        """The array of tables `key` (``[[where.key]]`` in TOML), each a Section.

        The i-th is named ``where.key[i]``; a single table counts as an array of one, and
        an absent key as an empty array.
        """
        _, value = self._raw(key, [])
        if isinstance(value, dict):
            value = [value]
        if not isinstance(value, list):
            raise ConfigError(f"{self.where}.{key} must be an array of tables, got {value!r}")
        return [Section(t, f"{self.where}.{key}[{i}]") for i, t in enumerate(value)]

    def point(self, key: str, default: Any = ...) -> tuple[float, float] | Any:
        """A point ``[x, y]``: a list of two numbers, returned as a tuple of floats."""
        present, value = self._raw(key, default)
        if not present:
            return value
        if isinstance(value, list | tuple) and len(value) == 2 and all(map(_is_number, value)):
            return (float(value[0]), float(value[1]))
        raise ConfigError(f"{self.where}.{key} must be a pair of numbers [x, y], got {value!r}")

    def number_list(self, key: str, default: Any = ...) -> tuple[float, ...] | Any:
        """A non-empty list of numbers, returned as a tuple of floats (a lone number is refused)."""
        present, value = self._raw(key, default)
        if not present:
            return value
        if isinstance(value, list | tuple) and value and all(map(_is_number, value)):
            return tuple(float(v) for v in value)
        raise ConfigError(f"{self.where}.{key} must be a non-empty list of numbers, got {value!r}")

    def key_data(self, key: str, default: Any = ...) -> np.ndarray | Any:
        """Raw data of a `jax.random` key (as ``jax.random.key_data`` gives it), as ``uint32``.

        The value is a non-empty list of integers in ``[0, 2**32)``; turn it back into a
        key with ``jax.random.wrap_key_data`` (or :func:`invglare._core.checks.as_key`).
        """
        present, value = self._raw(key, default)
        if not present:
            return value
        if isinstance(value, list | tuple) and value and all(map(_is_uint32, value)):
            return np.asarray(value, dtype=np.uint32)
        raise ConfigError(
            f"{self.where}.{key} must be a list of uint32 integers (jax.random.key_data), "
            f"got {value!r}"
        )

    def build(self, make: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Any:
        """``make(*args, **kwargs)`` (the constructor this table describes), its errors placed.

        A `ConfigError`, `PhysicsRangeError` or `InputDataError` raised while building is
        raised again, of the same type, with ``where: `` in front of its message.
        """
        try:
            return make(*args, **kwargs)
        except (ConfigError, PhysicsRangeError, InputDataError) as err:
            raise type(err)(f"{self.where}: {err}") from err

    def _raw(self, key: str, default: Any) -> tuple[bool, Any]:
        """(whether `key` is given, its value or `default`); `default` ``...`` means required."""
        self._known.append(key)
        if key in self.table:
            return True, self.table[key]
        if default is ...:
            raise ConfigError(f"[{self.where}] needs the key {key!r}")
        return False, default

    def finish(self) -> None:
        unknown = [k for k in self.table if k not in self._known]
        if unknown:
            raise ConfigError(
                f"[{self.where}] has unknown key {unknown[0]!r}; valid keys: "
                f"{', '.join(self._known)}"
            )


def _is_number(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


def _is_uint32(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool) and 0 <= x < 2**32


def check_sections(config: dict[str, Any], valid: tuple[str, ...], source: str) -> None:
    """Reject top-level tables that no command reads (usually a typo)."""
    for key in config:
        if key not in valid:
            raise ConfigError(
                f"{source}: unknown section [{key}]; valid sections: {', '.join(valid)}"
            )


#: The top-level tables of a model config (each kind's reader may accept fewer).
MODEL_SECTIONS = ("model", "output", "spectrum")


def precheck_model_config(path: str | os.PathLike[str]) -> dict[str, Any]:
    """A model config's TOML, its top-level tables and its ``model.kind`` checked before
    JAX loads (which takes seconds), so that a typo is reported at once; the kind's own
    reader checks the keys later. **Returns:** the parsed config. **Raises:** ConfigError.
    """
    config = load_toml(path)
    check_sections(config, MODEL_SECTIONS, str(path))
    if "model" not in config:
        raise ConfigError(f"{path}: no [model] section")
    with prefixed(str(path)):
        Section(config["model"], "model").get("kind", str, required=True)
    return config
