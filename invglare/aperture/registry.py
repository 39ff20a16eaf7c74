"""Shapes from configuration tables (TOML) and back.

A shape is written as a table with a `kind` and the constructor's arguments,
for example::

    [[model.shapes]]
    kind = "polygon"
    n_blades = 6
    diameter_mm = 4.0
    rounding = 0.3
    role = "open"        # optional on every shape: "open" or "block"

Valid kinds and keys (lengths in mm, angles in degrees, points as ``[x, y]``):

| kind      | required                            | optional                                 |
|-----------|-------------------------------------|------------------------------------------|
| `disk`    | `diameter_mm`                       | `center_mm`                              |
| `ellipse` | `diameter_mm`                       | `ellipticity`, `rotation_deg`, `center_mm` |
| `polygon` | `n_blades`, `diameter_mm`           | `rotation_deg`, `rounding`, `center_mm`  |
| `capsule` | `start_mm`, `end_mm`, `thickness_mm` |                                          |
| `image`   | `path`, `width_mm`                  | `center_mm`, `rotation_deg`              |
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from invglare.aperture.primitives import (
    ROLES,
    AbstractShape,
    Capsule,
    Disk,
    Ellipse,
    ImageMask,
    RegularPolygon,
)
from invglare.errors import ConfigError, InputDataError, PhysicsRangeError

#: kind name -> shape class.
SHAPE_KINDS: dict[str, type[AbstractShape]] = {
    "disk": Disk,
    "ellipse": Ellipse,
    "polygon": RegularPolygon,
    "capsule": Capsule,
    "image": ImageMask,
}

# Value types of the keys: "number" (int or float), "int", "point" ([x, y]), "str".
_KEY_TYPES = {
    "diameter_mm": "number",
    "ellipticity": "number",
    "rotation_deg": "number",
    "rounding": "number",
    "thickness_mm": "number",
    "width_mm": "number",
    "n_blades": "int",
    "center_mm": "point",
    "start_mm": "point",
    "end_mm": "point",
    "path": "str",
    "role": "role",
}

# kind -> (required keys, optional keys), in constructor order.
_KEYS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "disk": (("diameter_mm",), ("center_mm",)),
    "ellipse": (("diameter_mm",), ("ellipticity", "rotation_deg", "center_mm")),
    "polygon": (("n_blades", "diameter_mm"), ("rotation_deg", "rounding", "center_mm")),
    "capsule": (("start_mm", "end_mm", "thickness_mm"), ()),
    "image": (("path", "width_mm"), ("center_mm", "rotation_deg")),
}

_CLASS_TO_KIND = {cls: kind for kind, cls in SHAPE_KINDS.items()}


def _is_number(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


def _convert(key: str, value: Any, where: str) -> Any:
    """Check a config value's type and return it in the form the constructor takes."""
    kind = _KEY_TYPES[key]
    if kind == "number" and _is_number(value):
        return float(value)
    if kind == "int" and isinstance(value, int) and not isinstance(value, bool):
        return value
    if kind == "point" and isinstance(value, list | tuple) and len(value) == 2:
        if all(_is_number(v) for v in value):
            return (float(value[0]), float(value[1]))
    if kind == "str" and isinstance(value, str | Path):
        return str(value)
    if kind == "role" and value in ROLES:
        return value
    expected = {
        "number": "a number",
        "int": "an integer",
        "point": "a pair of numbers [x, y]",
        "str": "a string",
        "role": f"one of {list(ROLES)}",
    }[kind]
    raise ConfigError(f"{where}.{key} must be {expected}, got {value!r}")


def shape_from_config(
    table: dict[str, Any], where: str = "shape", base_dir: str | Path | None = None
) -> AbstractShape:
    """Build a shape from a configuration table such as ``{"kind": "disk", "diameter_mm": 4.0}``.

    **Arguments:**

    - `table`: the table; `kind` selects the shape (see :data:`SHAPE_KINDS`), the
      other keys are the shape's arguments, plus an optional `role`.
    - `where`: where the table sits in the configuration (e.g. ``"model.shapes[0]"``),
      used in error messages.
    - `base_dir`: directory that a relative image `path` is resolved against
      (normally the directory of the config file); default the working directory.

    **Raises:** `ConfigError` for an unknown kind or key, a missing key or a value
    of the wrong type; `PhysicsRangeError` / `InputDataError` (prefixed with
    `where`) for out-of-range values or a bad image file.
    """
    if not isinstance(table, dict):
        raise ConfigError(f"{where} must be a table with a 'kind', got {table!r}")
    if "kind" not in table:
        raise ConfigError(f"{where} has no 'kind'; valid kinds: {', '.join(SHAPE_KINDS)}")
    kind = table["kind"]
    if kind not in SHAPE_KINDS:
        raise ConfigError(
            f"{where}.kind = {kind!r} is not a shape kind; valid kinds: {', '.join(SHAPE_KINDS)}"
        )
    required, optional = _KEYS[kind]
    valid = ("kind", *required, *optional, "role")
    for key in table:
        if key not in valid:
            raise ConfigError(
                f"{where}: unknown key {key!r} for a {kind} shape; valid keys: {', '.join(valid)}"
            )
    missing = [key for key in required if key not in table]
    if missing:
        raise ConfigError(
            f"{where}: a {kind} shape needs {', '.join(repr(k) for k in missing)} "
            f"(required keys: {', '.join(required)})"
        )
    args = {key: _convert(key, table[key], where) for key in table if key != "kind"}
    try:
        if kind == "image":
            path = Path(args.pop("path"))
            if base_dir is not None and not path.is_absolute():
                path = Path(base_dir) / path
            return ImageMask.from_file(path, **args)
        return SHAPE_KINDS[kind](**args)
    except (PhysicsRangeError, InputDataError, ConfigError) as err:
        raise type(err)(f"{where}: {err}") from err


def _plain(value: Any) -> Any:
    """A JSON/TOML-friendly version of a concrete array value."""
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        return float(arr)
    return [float(v) for v in arr]


def shape_to_config(shape: AbstractShape) -> dict[str, Any]:
    """The configuration table of a shape (the inverse of :func:`shape_from_config`).

    Values are plain Python floats / lists, ready for TOML or JSON (e.g. an EXR
    header). An image mask stores the path it was read from; one built from an
    array has no path and raises `ConfigError`.
    """
    kind = _CLASS_TO_KIND.get(type(shape))
    if kind is None:
        raise ConfigError(
            f"cannot write a {type(shape).__name__} as configuration; "
            f"known shapes: {', '.join(c.__name__ for c in SHAPE_KINDS.values())}"
        )
    required, optional = _KEYS[kind]
    table: dict[str, Any] = {"kind": kind}
    for key in (*required, *optional):
        if key == "path":
            if shape.source is None:
                raise ConfigError(
                    "an image mask built from an array has no path to write; "
                    "use ImageMask.from_file"
                )
            table["path"] = shape.source
        elif key == "n_blades":
            table[key] = int(shape.n_blades)
        else:
            table[key] = _plain(getattr(shape, key))
    table["role"] = shape.role
    return table
