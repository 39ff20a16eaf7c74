"""The reader of shape tables (``[[model.shapes]]``): :func:`shape_from_config`.

The kinds and keys are those of :mod:`invglare.aperture.shapes.schema`, whose
:func:`~invglare.aperture.shapes.schema.shape_to_config` writes what this reads.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from invglare._core.checks import choose
from invglare.aperture.shapes.primitives import ROLES, AbstractShape, ImageMask
from invglare.aperture.shapes.schema import KEY_KINDS, SHAPE_KEYS, SHAPE_KINDS
from invglare.config.section import Section
from invglare.errors import ConfigError

# How a value of each kind of key is read; `None` as the default: absent, the
# constructor's default applies.
_READERS = {
    "number": lambda sec, key, default: sec.get(key, float, default),
    "int": lambda sec, key, default: sec.get(key, int, default),
    "point": Section.point,
    "path": lambda sec, key, default: _path(sec.get(key, (str, Path), default)),
}


def _path(value: str | Path | None) -> str | None:
    return None if value is None else str(value)


def shape_from_config(
    table: dict[str, Any], where: str = "shape", base_dir: str | Path | None = None
) -> AbstractShape:
    """Build a shape from a configuration table such as ``{"kind": "disk", "diameter_mm": 4.0}``.

    **Arguments:**

    - `table`: the table; `kind` selects the shape (see
      :data:`~invglare.aperture.shapes.schema.SHAPE_KINDS`), the other keys are the
      shape's arguments, plus an optional `role` (``"open"`` or ``"block"``).
    - `where`: where the table sits in the configuration (e.g. ``"model.shapes[0]"``),
      used in error messages.
    - `base_dir`: directory that a relative image `path` is resolved against
      (normally the directory of the config file); default the working directory.

    **Returns:** the shape (a :class:`~invglare.aperture.AbstractShape`).

    **Raises:** `ConfigError` for an unknown kind or key, a missing key or a value
    of the wrong type; `PhysicsRangeError` / `InputDataError` (prefixed with
    `where`) for out-of-range values or a bad image file.

    **Example:**

    ```python
    shape_from_config({"kind": "polygon", "n_blades": 6, "diameter_mm": 4.0}, "model.shapes[0]")
    ```
    """
    sec = Section(table, where)
    if "kind" not in sec.table:
        raise ConfigError(f"[{where}] needs the key 'kind'; valid kinds: {', '.join(SHAPE_KINDS)}")
    kind = sec.choice("kind", tuple(SHAPE_KINDS), ...)
    required, optional = SHAPE_KEYS[kind]
    sec.only("kind", *required, *optional, "role")
    args = {}
    for key in (*required, *optional):
        value = _READERS[KEY_KINDS[key]](sec, key, ... if key in required else None)
        if value is not None:
            args[key] = value
    role = sec.get("role", str, None)
    if role is not None:
        args["role"] = choose(f"{where}.role", role, ROLES)
    sec.finish()
    if kind == "image":
        path = Path(args.pop("path"))
        if base_dir is not None and not path.is_absolute():
            path = Path(base_dir) / path
        return sec.build(ImageMask.from_file, path, **args)
    return sec.build(SHAPE_KINDS[kind], **args)


def image_masks(
    top: Section, roles: dict[str, str], where: str, base_dir: str | Path | None
) -> dict[str, ImageMask | None]:
    """The optional image tables of an aperture's section (``obstacle_image``,
    ``pupil_image``, ...): ``{name: ImageMask or None}``, each with its default `role`
    from `roles`; a table names no `kind` (it is an image by its key)."""
    images: dict[str, ImageMask | None] = {}
    for name, role in roles.items():
        table = top.get(name, dict, None)
        if table is not None and "kind" in table:
            raise ConfigError(f"{where}.{name} is an image: drop its key 'kind'")
        images[name] = (
            None
            if table is None
            else shape_from_config(
                {"kind": "image", "role": role, **table}, f"{where}.{name}", base_dir
            )
        )
    return images
