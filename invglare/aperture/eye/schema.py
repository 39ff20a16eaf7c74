"""The configuration tables of an eye, and the writer :func:`eye_to_config`.

The tables' keys and value kinds are listed here once: :func:`eye_to_config` writes
them and :func:`invglare.config.eye.eye_from_config` reads them (the config tier reads;
the eye writes its own table).
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

from invglare.aperture._plain import plain
from invglare.aperture.eye.aperture import EyeAperture
from invglare.aperture.shapes.schema import shape_to_config
from invglare.errors import ConfigError

# The keys of each component's table, in constructor order, with the kind of their values:
# "number", "int", "point" ([x, y]), "str", "key" (a list of uint32 key data).

#: Keys of ``[eye.pupil]``.
PUPIL_KEYS = {
    "diameter_mm": "number",
    "ellipticity": "number",
    "rotation_deg": "number",
    "decentration_mm": "point",
}
#: Keys of ``[eye.lids]``.
LIDS_KEYS = {
    "upper_opening_mm": "number",
    "lower_opening_mm": "number",
    "upper_tilt_deg": "number",
    "lower_tilt_deg": "number",
    "curvature_per_mm": "number",
}
#: Keys of ``[eye.lashes_upper]`` and ``[eye.lashes_lower]``.
LASH_KEYS = {
    "count": "number",
    "n_max": "int",
    "mean_angle_deg": "number",
    "angular_spread_deg": "number",
    "spacing_jitter": "number",
    "thickness_mm": "number",
    "length_mm": "number",
    "curvature_per_mm": "number",
    "root_span_mm": "number",
    "length_spread": "number",
    "thickness_spread": "number",
    "segments": "int",
    "key_data": "key",
}
#: Keys of each ``[[eye.particles]]``.
PARTICLE_KEYS = {
    "region": "str",
    "count": "number",
    "n_max": "int",
    "radius_mean_mm": "number",
    "radius_spread": "number",
    "region_radius_mm": "number",
    "key_data": "key",
}
#: Keys of ``[eye.gratings]``.
GRATING_KEYS = {
    "count": "number",
    "n_max": "int",
    "spacing_mm": "number",
    "line_thickness_mm": "number",
    "line_length_mm": "number",
    "inner_radius_mm": "number",
    "outer_radius_mm": "number",
    "lines_per_grating": "int",
    "key_data": "key",
}
#: Keys of an eye table (sub-tables, a list of particle tables, and the seed). The image
#: tables take the keys of an image shape (``path``, ``width_mm``, ``center_mm``,
#: ``rotation_deg``, ``role``; :mod:`invglare.aperture.shapes.schema`) without ``kind``.
EYE_KEYS = (
    "pupil",
    "lids",
    "lashes_upper",
    "lashes_lower",
    "particles",
    "gratings",
    "obstacle_image",
    "pupil_image",
    "seed",
)
#: The role an eye's image has when its table gives none: an obstacle image shows the
#: plane's transmission (white passes), a pupil image the opening (white passes).
IMAGE_DEFAULT_ROLES = {"obstacle_image": "block", "pupil_image": "open"}

#: ``fold_in`` tags deriving each component's key from the eye's seed (the i-th particle
#: population's is ``SEED_TAGS["particles"] + i``).
SEED_TAGS = {"lashes_upper": 1, "lashes_lower": 2, "gratings": 3, "particles": 100}


def _component_table(component, keys: dict[str, str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, kind in keys.items():
        if kind == "key":
            out[key] = [int(v) for v in np.asarray(jax.random.key_data(component.key)).ravel()]
        elif kind in ("int", "str"):
            out[key] = getattr(component, key)
        else:
            out[key] = plain(getattr(component, key))
    return out


def eye_to_config(eye: EyeAperture) -> dict[str, Any]:
    """The configuration table of an eye (the inverse of the reader `eye_from_config`).

    Values are plain Python floats, ints, strings and lists (ready for TOML / JSON);
    every random component carries its `key_data`, so
    :func:`invglare.config.eye.eye_from_config` of the table rasterises identically.
    Stamp-window overrides are not written (they belong to a grid, not to the eye).

    **Raises:** `ConfigError` unless `eye` is an :class:`EyeAperture`.

    **Example:**

    ```python
    table = eye_to_config(night_eye(0))
    table["pupil"]   # {'diameter_mm': 7.0, 'ellipticity': 0.0, 'rotation_deg': 0.0, ...}
    ```
    """
    if not isinstance(eye, EyeAperture):
        raise ConfigError(f"eye_to_config needs an EyeAperture, got {type(eye).__name__}")
    table: dict[str, Any] = {"pupil": _component_table(eye.pupil, PUPIL_KEYS)}
    if eye.lids is not None:
        table["lids"] = _component_table(eye.lids, LIDS_KEYS)
    if eye.upper_lashes is not None:
        table["lashes_upper"] = _component_table(eye.upper_lashes, LASH_KEYS)
    if eye.lower_lashes is not None:
        table["lashes_lower"] = _component_table(eye.lower_lashes, LASH_KEYS)
    for name in IMAGE_DEFAULT_ROLES:
        image = getattr(eye, name)
        if image is not None:
            table[name] = {k: v for k, v in shape_to_config(image).items() if k != "kind"}
    if eye.particles:
        table["particles"] = [_component_table(p, PARTICLE_KEYS) for p in eye.particles]
    if eye.gratings is not None:
        table["gratings"] = _component_table(eye.gratings, GRATING_KEYS)
    return table
