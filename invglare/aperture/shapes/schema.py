"""The configuration tables of shapes, and the writer :func:`shape_to_config`.

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

The reader of these tables is :func:`invglare.config.shapes.shape_from_config` (the
config tier reads; the shapes write their own tables).
"""

from __future__ import annotations

from typing import Any

from invglare.aperture._plain import plain
from invglare.aperture.shapes.primitives import (
    AbstractShape,
    Capsule,
    Disk,
    Ellipse,
    ImageMask,
    RegularPolygon,
)
from invglare.errors import ConfigError

#: kind name -> shape class.
SHAPE_KINDS: dict[str, type[AbstractShape]] = {
    "disk": Disk,
    "ellipse": Ellipse,
    "polygon": RegularPolygon,
    "capsule": Capsule,
    "image": ImageMask,
}

#: How each key's value is written: "number" (int or float), "int", "point" ([x, y]),
#: "path" (a string, relative to the config file). Every shape also takes `role`.
KEY_KINDS: dict[str, str] = {
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
    "path": "path",
}

#: kind -> (required keys, optional keys), in constructor order (`role` aside).
SHAPE_KEYS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "disk": (("diameter_mm",), ("center_mm",)),
    "ellipse": (("diameter_mm",), ("ellipticity", "rotation_deg", "center_mm")),
    "polygon": (("n_blades", "diameter_mm"), ("rotation_deg", "rounding", "center_mm")),
    "capsule": (("start_mm", "end_mm", "thickness_mm"), ()),
    "image": (("path", "width_mm"), ("center_mm", "rotation_deg")),
}

_CLASS_TO_KIND = {cls: kind for kind, cls in SHAPE_KINDS.items()}


def shape_to_config(shape: AbstractShape) -> dict[str, Any]:
    """The configuration table of a shape (the inverse of the reader `shape_from_config`).

    Values are plain Python floats / lists, ready for TOML or JSON (e.g. an EXR
    header). An image mask stores the path it was read from; one built from an
    array has no path and raises `ConfigError`.

    **Example:**

    ```python
    shape_to_config(Disk(4.0))
    # {'kind': 'disk', 'diameter_mm': 4.0, 'center_mm': [0.0, 0.0], 'role': 'open'}
    ```
    """
    kind = _CLASS_TO_KIND.get(type(shape))
    if kind is None:
        raise ConfigError(
            f"cannot write a {type(shape).__name__} as configuration; "
            f"known shapes: {', '.join(c.__name__ for c in SHAPE_KINDS.values())}"
        )
    required, optional = SHAPE_KEYS[kind]
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
            table[key] = plain(getattr(shape, key))
    table["role"] = shape.role
    return table
