"""The reader of eye tables (``[model.eye]``): :func:`eye_from_config`.

The keys are those of :mod:`invglare.aperture.eye.schema`, whose
:func:`~invglare.aperture.eye.eye_to_config` writes what this reads.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import jax

from invglare._core.memory import check_memory
from invglare.aperture.eye import EyeAperture, Eyelashes, Eyelids, Gratings, Particles, Pupil
from invglare.aperture.eye.lash_layout import LashLayout
from invglare.aperture.eye.schema import (
    EYE_KEYS,
    GRATING_KEYS,
    IMAGE_DEFAULT_ROLES,
    LASH_KEYS,
    LAYOUT_KEYS,
    LIDS_KEYS,
    PARTICLE_KEYS,
    PUPIL_KEYS,
    SEED_TAGS,
)
from invglare.config.section import Section
from invglare.config.shapes import image_masks
from invglare.errors import ConfigError

# How a value of each kind of key is read (see the schema); `None` as the default: absent,
# the constructor's default applies.
_READERS = {
    "number": lambda sec, key, default: sec.get(key, float, default),
    "int": lambda sec, key, default: sec.get(key, int, default),
    "str": lambda sec, key, default: sec.get(key, str, default),
    "point": Section.point,
    "key": Section.key_data,
    "layout": lambda sec, key, default: _layout(sec, key),
}


def _layout(parent: Section, key: str) -> LashLayout | str | None:
    """A row's ``layout``: a table of one list of numbers per leaf (all required), or the
    string ``"drawn"`` (the key's draw, frozen into a layout once the row is built)."""
    value = parent.get(key, (str, dict), None)
    if value is None:
        return None
    if isinstance(value, str):
        if value != "drawn":
            raise ConfigError(
                f"{parent.where}.{key} must be a table of per-lash lists or 'drawn', got {value!r}"
            )
        return value
    sec = parent.section(key)
    sec.only(*LAYOUT_KEYS)
    values = {leaf: sec.number_list(leaf) for leaf in LAYOUT_KEYS}
    sec.finish()
    sizes = {len(v) for v in values.values()}
    if len(sizes) != 1:
        raise ConfigError(
            f"{sec.where}: every list must have one entry per lash, got lengths "
            + ", ".join(f"{k} {len(v)}" for k, v in values.items())
        )
    return sec.build(LashLayout, **values)


def eye_from_config(
    table: dict[str, Any], where: str = "eye", base_dir: str | Path | None = None
) -> EyeAperture:
    """Build an :class:`~invglare.aperture.eye.EyeAperture` from a TOML-like table.

    **Arguments:**

    - `table`: a dict with the sub-tables below; only `pupil` is required.
    - `where`: where the table sits in the configuration (e.g. ``"model.eye"``), for
      error messages.
    - `base_dir`: what a relative image `path` is resolved against (the config's folder).

    ```toml
    [eye]
    seed = 7                     # int; derives every component's key (default 0)
    [eye.pupil]                  # diameter_mm (required), ellipticity, rotation_deg,
    diameter_mm = 6.0            #   decentration_mm = [x, y]
    [eye.lids]                   # upper/lower_opening_mm, upper/lower_tilt_deg,
    upper_opening_mm = 4.0       #   curvature_per_mm
    [eye.lashes_upper]           # count (required), n_max, mean_angle_deg,
    count = 60                   #   angular_spread_deg, spacing_jitter, thickness_mm,
                                 #   length_mm, curvature_per_mm, root_span_mm,
                                 #   length_spread, thickness_spread, segments, key_data
    [eye.lashes_upper.layout]    # optional: each lash's own values, one list entry per lash
    root_mm = [...]              #   (n_max entries each): root_mm, angle_deg, length_mm,
                                 #   thickness_mm, curvature_per_mm (all required); or
                                 #   layout = "drawn" in [eye.lashes_upper]: the key's draw
    [eye.lashes_lower]           # as lashes_upper
    [[eye.particles]]            # region and count (required), n_max, radius_mean_mm,
    region = "lens_nucleus"      #   radius_spread, region_radius_mm, key_data
    count = 750
    [eye.gratings]               # count (required), n_max, spacing_mm,
    count = 200                  #   line_thickness_mm, line_length_mm, inner_radius_mm,
                                 #   outer_radius_mm, lines_per_grating, key_data
    [eye.obstacle_image]         # any picture of the obstacle (Kakimoto's t_o): path and
    path = "lashes.png"          #   width_mm (required), center_mm, rotation_deg, role
    width_mm = 14.0              #   ("block": white passes light, the default; "open":
                                 #   white stops it); clear outside the picture
    [eye.pupil_image]            # a picture of the pupil (white passes), multiplying the
    path = "pupil.png"           #   procedural pupil; same keys (role default "open")
    width_mm = 6.0
    ```

    `n_max` defaults to the count rounded up. A component's key is
    ``fold_in(key(seed), tag)`` unless it gives `key_data` (what
    :func:`~invglare.aperture.eye.eye_to_config` writes, so that a written eye is
    reproduced exactly).

    **Returns:** the eye.

    **Raises:** `ConfigError` naming the key for an unknown key (listing the valid
    ones), a missing key or a value of the wrong type; `PhysicsRangeError` for
    values out of range, prefixed with where they are.

    **Example:**

    ```python
    eye = eye_from_config(load_toml("examples/eye_daylight.toml")["model"]["eye"], "model.eye")
    ```
    """
    top = Section(table, where)
    top.only(*EYE_KEYS)
    seed = top.get("seed", int, 0)
    root = jax.random.key(seed)
    pupil = _component(top.section("pupil", required=True), Pupil, PUPIL_KEYS, ("diameter_mm",))
    lids_sec = top.section("lids")
    lids = None if lids_sec is None else _component(lids_sec, Eyelids, LIDS_KEYS, ())
    lashes = {}
    for name, lid in (("lashes_upper", "upper"), ("lashes_lower", "lower")):
        sec = top.section(name)
        lashes[lid] = None
        if sec is not None:
            key = jax.random.fold_in(root, SEED_TAGS[name])
            lashes[lid] = _component(sec, Eyelashes, LASH_KEYS, ("count",), key, lid=lid)
    particles = tuple(
        _component(
            sec,
            Particles,
            PARTICLE_KEYS,
            ("region", "count"),
            jax.random.fold_in(root, SEED_TAGS["particles"] + i),
        )
        for i, sec in enumerate(top.sections("particles"))
    )
    gratings_sec, gratings = top.section("gratings"), None
    if gratings_sec is not None:
        key = jax.random.fold_in(root, SEED_TAGS["gratings"])
        gratings = _component(gratings_sec, Gratings, GRATING_KEYS, ("count",), key)
    images = image_masks(top, IMAGE_DEFAULT_ROLES, where, base_dir)
    top.finish()
    return top.build(
        EyeAperture,
        pupil=pupil,
        lids=lids,
        upper_lashes=lashes["upper"],
        lower_lashes=lashes["lower"],
        particles=particles,
        gratings=gratings,
        **images,
    )


def _component(
    sec: Section,
    cls: type,
    keys: dict[str, str],
    required: tuple[str, ...],
    key: Any = None,
    **fixed: Any,
) -> Any:
    """One component of the eye from its table (`key`: its key unless the table has one).

    A pool's `n_max` defaults to its count rounded up.
    """
    sec.only(*keys)
    args = dict(fixed)
    for name, kind in keys.items():
        value = _READERS[kind](sec, name, ... if name in required else None)
        if value is not None:
            args[name] = value
    sec.finish()
    if "key_data" in args:
        key = _wrap_key(args.pop("key_data"), f"{sec.where}.key_data")
    if key is not None:
        args["key"] = key
    if "count" in args and "n_max" not in args:
        args["n_max"] = max(1, math.ceil(args["count"]))
    if "n_max" in args:
        n = args["n_max"]
        check_memory(
            float(n) * POOL_BYTES_PER_ELEMENT,
            f"{sec.where}.n_max = {n} (a pool of {n} elements, each drawn and rasterised)",
        )
    drawn = args.get("layout") == "drawn"
    if drawn:
        del args["layout"]
    built = sec.build(cls, **args)
    return built.with_layout() if drawn else built


#: A lower bound of the memory one pool element (a lash, a particle, a grating) takes: its
#: drawn values and its raster on an aperture grid of at least 32² float32 samples.
POOL_BYTES_PER_ELEMENT = 4 * 32**2


def _wrap_key(data, where: str) -> jax.Array:
    try:
        return jax.random.wrap_key_data(data)
    except (TypeError, ValueError) as err:
        raise ConfigError(
            f"{where} = {data.tolist()} is not the data of a jax.random key ({err})"
        ) from err
