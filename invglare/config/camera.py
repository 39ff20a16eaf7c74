"""The reader of camera tables (``[model.camera]``): :func:`camera_from_config`.

:func:`invglare.aperture.camera.camera_to_config` writes what this reads.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from invglare.aperture.camera import CameraAperture, CrossScreen, Diaphragm, Dust
from invglare.aperture.eye.schema import IMAGE_DEFAULT_ROLES
from invglare.config.section import Section
from invglare.config.shapes import image_masks


def camera_from_config(
    table: dict[str, Any], where: str = "camera", base_dir: str | Path | None = None
) -> CameraAperture:
    """Build a :class:`~invglare.aperture.camera.CameraAperture` from a configuration table.

    **Arguments:**

    - `table`: the table, with the keys below (lengths in mm, angles in degrees).
    - `where`: where the table sits in the configuration (e.g. ``"model.camera"``), for
      error messages.

    Keys (lengths in mm, angles in degrees):

    - `seed` (optional, an integer): the seed of the dust pattern;
    - `[diaphragm]` (required): `n_blades` (an integer), `f_number`, `focal_length_mm`;
      optional `rotation_deg`, `rounding`;
    - `[cross_screen]` (optional): `angles_deg` (a non-empty list), `spacing_mm`,
      `duty_cycle`; optional `line_offset_mm`;
    - `[dust]` (optional): `density`, `opacity`, `feature_size_mm`; optional `octaves`
      (an integer), `edge_softness`;
    - `[obstacle_image]`, `[pupil_image]` (optional): a picture (`path` relative to
      `base_dir`, `width_mm`; optional `center_mm`, `rotation_deg`, `role`) of an obstacle
      in front of the lens (white passes light, role ``"block"``) or of the opening
      (white passes, role ``"open"``), as for the eye.

    For example ``[model.camera.diaphragm]`` with ``n_blades = 6``, ``f_number = 8.0``,
    ``focal_length_mm = 50.0`` and ``[model.camera.cross_screen]`` with
    ``angles_deg = [0.0, 90.0]``, ``spacing_mm = 0.2``, ``duty_cycle = 0.1``.

    **Returns:** the camera.

    **Raises:** `ConfigError` for an unknown or missing key (naming it and listing
    the valid keys) or a value of the wrong type; `PhysicsRangeError` (prefixed
    with `where`) for out-of-range values.

    **Example:**

    ```python
    camera = camera_from_config(
        {"diaphragm": {"n_blades": 6, "f_number": 8.0, "focal_length_mm": 50.0}}
    )
    ```
    """
    top = Section(table, where)
    top.only("diaphragm", "cross_screen", "dust", "seed", *IMAGE_DEFAULT_ROLES)
    seed = top.get("seed", int, 0)
    diaphragm = _args(
        top.section("diaphragm", required=True),
        n_blades=(int, ...),
        f_number=(float, ...),
        focal_length_mm=(float, ...),
        rotation_deg=(float, None),
        rounding=(float, None),
    )
    screen = _args(
        top.section("cross_screen"),
        angles_deg=("list", ...),
        spacing_mm=(float, ...),
        duty_cycle=(float, ...),
        line_offset_mm=(float, None),
    )
    dust = _args(
        top.section("dust"),
        density=(float, ...),
        opacity=(float, ...),
        feature_size_mm=(float, ...),
        octaves=(int, None),
        edge_softness=(float, None),
    )
    images = image_masks(top, IMAGE_DEFAULT_ROLES, where, base_dir)
    top.finish()
    # Range errors are placed at the camera's table (``camera: diaphragm n_blades ...``).
    return CameraAperture(
        top.build(Diaphragm, **diaphragm),
        None if screen is None else top.build(CrossScreen, **screen),
        None if dust is None else top.build(Dust, **dust, key=seed),
        **images,
    )


def _args(sec: Section | None, **spec: tuple[Any, Any]) -> dict[str, Any] | None:
    """Constructor arguments from a sub-table (None without one): `spec` maps each key to
    (kind, default).

    A kind is a Python type for :meth:`Section.get` or ``"list"`` (a non-empty list of
    numbers); the default ``...`` makes the key required, and an absent key with the
    default None is left to the constructor.
    """
    if sec is None:
        return None
    sec.only(*spec)
    args = {}
    for key, (kind, default) in spec.items():
        if kind == "list":
            value = sec.number_list(key, default)
        else:
            value = sec.get(key, kind, default)
        if value is not None:
            args[key] = value
    sec.finish()
    return args
