"""The holographic eye's config (``model.kind = "holographic"``, Novosad & Ziegler)."""

from __future__ import annotations

import math
from typing import Any

import jax
import numpy as np

from invglare._core.grids import check_wavelengths_nm
from invglare.config.eye import eye_from_config
from invglare.config.raster import KEEP_GRID, GridRequest, square_npix
from invglare.config.section import MODEL_SECTIONS, Section, check_sections
from invglare.errors import ConfigError, PhysicsRangeError, prefixed
from invglare.models.holographic import (
    _GEOMETRY_KEYS,
    DEFAULT_RGB_NM,
    LAYERS,
    MODES,
    HolographicEye,
)
from invglare.optics.holographic import PHASES, Frustum, Spectacles, TearFilm


def _read_key(sec, where: str):
    if "seed" in sec.table and "key_data" in sec.table:
        raise ConfigError(f"{where}: give seed or key_data, not both")
    key_data = sec.get("key_data", list, None)
    if key_data is not None:
        if not key_data or not all(
            isinstance(v, int) and not isinstance(v, bool) and 0 <= v < 2**32 for v in key_data
        ):
            raise ConfigError(
                f"{where}.key_data must be a list of uint32 integers, got {key_data!r}"
            )
        return jax.random.wrap_key_data(np.asarray(key_data, np.uint32))
    return sec.get("seed", int, 0)


def _read_tear_film(table: Any, where: str) -> TearFilm:
    sec = Section(table, where)
    args: dict[str, Any] = {
        "pattern": sec.get("pattern", str, "sinusoid"),
        "amplitude_um": sec.get("amplitude_um", float, required=True),
        "scale_mm": sec.get("scale_mm", float, required=True),
        "key": _read_key(sec, where),
    }
    for name in (
        "angle_deg",
        "thickness_um",
        "irregularity_growth_per_s",
        "thinning_um_per_s",
        "breakup_time_s",
        "breakup_growth_mm_per_s",
        "breakup_edge_mm",
        "breakup_region_mm",
        "refractive_index",
    ):
        value = sec.get(name, float, None)
        if value is not None:
            args[name] = value
    for name in ("n_modes", "breakup_spots"):
        value = sec.get(name, int, None)
        if value is not None:
            args[name] = value
    sec.finish()
    try:
        return TearFilm(**args)
    except (ConfigError, PhysicsRangeError) as err:
        raise type(err)(f"{where}: {err}") from err


def holographic_from_config(
    config: dict[str, Any],
    base_dir: Any = None,
    grid: GridRequest = KEEP_GRID,
    source: str = "config",
) -> HolographicEye:
    """Build a :class:`HolographicEye` from a model config (``model.kind = "holographic"``).

    **Arguments:**

    - `config`: the parsed TOML (sections ``model``, ``output``, ``spectrum``).
    - `base_dir`: where relative paths would be resolved (the model has none; accepted for
      the common interface).
    - `npix`, `pixel_scale_deg`, `wavelengths_nm`: overrides of ``output.npix``,
      ``output.pixel_scale_deg`` and ``spectrum.wavelengths_nm``.

    ```toml
    [model]
    kind = "holographic"
    window_mm = 8.0                # aperture window at the shortest wavelength (or
                                   #   output.pixel_scale_deg)
    focus_distance_m = 2.0         # > 0, inf for a relaxed eye (or accommodation_d)
    depth_m = 2.0                  # the scene's depth without a depth buffer (or depth_mm)
    mode = "iterations"            # or "speckle_free"
    iterations = 64
    phases = "uniform"             # or "quaternary"
    input_step = 1                 # output pixels per input pixel
    depth_layers = 1               # or "auto" (from the frustum's near and far planes)
    psf_tiles = 1                  # speckle-free PSF tiles per axis
    memory_budget_mb = 1024.0
    max_pupil_mm = 6.0             # largest pupil a fit may reach (window check)
    layer_npix = 256               # the layers' grid (default: what the pupil's light needs)
    [model.layers]                 # switches of spectacles, lashes, tear_film, pupil, lens
    lashes = true
    tear_film = true
    [model.geometry]               # lash_distance_mm, cornea_distance_mm,
    lash_distance_mm = 8.0         #   spectacle_distance_mm
    [model.frustum]                # fov_x_deg, near_m, far_m, depth_encoding,
    depth_encoding = "linear"      #   depth_unit_mm
    [model.eye]                    # invglare.aperture.eye.eye_from_config
    [model.tear_film]              # pattern, amplitude_um, scale_mm, angle_deg, n_modes,
    pattern = "random"             #   thickness_um, irregularity_growth_per_s,
    amplitude_um = 0.1             #   thinning_um_per_s, breakup_time_s, breakup_spots,
    scale_mm = 0.5                 #   breakup_growth_mm_per_s, breakup_edge_mm,
                                   #   breakup_region_mm, refractive_index, seed / key_data
    [model.spectacles]             # sphere_d, cylinder_d, axis_deg
    [output]
    npix = 512
    [spectrum]
    wavelengths_nm = [640.0, 550.0, 460.0]
    ```

    **Raises:** `ConfigError` naming the key for unknown keys, wrong types or choices;
    `PhysicsRangeError` for values out of range (a focus distance <= 0, a window too
    small, a lens or tear film the grid aliases).
    """
    del base_dir  # no file references
    check_sections(config, MODEL_SECTIONS, source)
    npix = square_npix(grid.npix, source)
    pixel_scale_deg, wavelengths_nm = grid.pixel_scale_deg, grid.wavelengths_nm
    model = Section(config.get("model", {}), "model")
    kind = model.get("kind", str, required=True)
    if kind != "holographic":
        raise ConfigError(
            f"model.kind = {kind!r}; holographic_from_config reads kind = 'holographic'"
        )
    eye = eye_from_config(model.get("eye", dict, required=True), "model.eye")
    kwargs: dict[str, Any] = {}
    if "focus_distance_m" in model.table and "accommodation_d" in model.table:
        raise ConfigError("model: give focus_distance_m or accommodation_d, not both")
    focus_m = model.get("focus_distance_m", float, None)
    acc = model.get("accommodation_d", float, None)
    if focus_m is not None:
        if not focus_m > 0 or math.isnan(focus_m):
            raise PhysicsRangeError(
                f"model.focus_distance_m must be > 0 (inf for a relaxed eye), got {focus_m!r}"
            )
        kwargs["focus_distance_mm"] = focus_m * 1000.0
    elif acc is not None:
        if not math.isfinite(acc):
            raise PhysicsRangeError(f"model.accommodation_d must be finite, got {acc!r}")
        kwargs["focus_distance_mm"] = math.inf if acc == 0 else 1000.0 / acc
    if "depth_m" in model.table and "depth_mm" in model.table:
        raise ConfigError("model: give depth_m or depth_mm, not both")
    depth_m = model.get("depth_m", float, None)
    depth_mm = model.get("depth_mm", float, None)
    if depth_m is not None:
        kwargs["depth_mm"] = depth_m * 1000.0
    elif depth_mm is not None:
        kwargs["depth_mm"] = depth_mm
    window = model.get("window_mm", float, None)
    kwargs["mode"] = model.choice("mode", MODES, "iterations")
    kwargs["iterations"] = model.get("iterations", int, 16)
    kwargs["phases"] = model.choice("phases", PHASES, "uniform")
    kwargs["input_step"] = model.get("input_step", int, 1)
    layers_value = model.get("depth_layers", (int, str), 1)
    if isinstance(layers_value, str) and layers_value != "auto":
        raise ConfigError(
            f"model.depth_layers must be an integer >= 1 or 'auto', got {layers_value!r}"
        )
    kwargs["depth_layers"] = layers_value
    kwargs["psf_tiles"] = model.get("psf_tiles", int, 1)
    kwargs["memory_budget_mb"] = model.get("memory_budget_mb", float, 1024.0)
    kwargs["max_pupil_mm"] = model.get("max_pupil_mm", float, None)
    kwargs["layer_npix"] = model.get("layer_npix", int, None)
    switches = Section(model.get("layers", dict, {}), "model.layers")
    defaults = {"spectacles": False, "lashes": True, "tear_film": True, "pupil": True, "lens": True}
    on = [name for name in LAYERS if switches.get(name, bool, defaults[name])]
    switches.finish()
    kwargs["layers"] = tuple(on)
    geometry = Section(model.get("geometry", dict, {}), "model.geometry")
    for name in _GEOMETRY_KEYS:
        value = geometry.get(name, float, None)
        if value is not None:
            kwargs[name] = value
    geometry.finish()
    fr = Section(model.get("frustum", dict, {}), "model.frustum")
    near_m, far_m = fr.get("near_m", float, None), fr.get("far_m", float, None)
    try:
        kwargs["frustum"] = Frustum(
            fov_x_deg=fr.get("fov_x_deg", float, None),
            near_mm=None if near_m is None else near_m * 1000.0,
            far_mm=None if far_m is None else far_m * 1000.0,
            depth_encoding=fr.choice(
                "depth_encoding", ("linear", "distance", "normalised", "linear01"), "linear"
            ),
            depth_unit_mm=fr.get("depth_unit_mm", float, 1000.0),
        )
    except (ConfigError, PhysicsRangeError) as err:
        raise type(err)(f"model.frustum: {err}") from err
    fr.finish()
    film_table = model.get("tear_film", dict, None)
    if film_table is not None:
        kwargs["tear_film"] = _read_tear_film(film_table, "model.tear_film")
    spec_table = model.get("spectacles", dict, None)
    if spec_table is not None:
        sp = Section(spec_table, "model.spectacles")
        try:
            kwargs["spectacles"] = Spectacles(
                sp.get("sphere_d", float, 0.0),
                sp.get("cylinder_d", float, 0.0),
                sp.get("axis_deg", float, 0.0),
            )
        except PhysicsRangeError as err:
            raise PhysicsRangeError(f"model.spectacles: {err}") from err
        sp.finish()
    model.finish()
    output = Section(config.get("output", {}), "output")
    out_npix = output.get("npix", int, 512)
    scale = output.get("pixel_scale_deg", float, None)
    output.finish()
    spectrum = Section(config.get("spectrum", {}), "spectrum")
    lams = spectrum.get("wavelengths_nm", (float, list), list(DEFAULT_RGB_NM))
    spectrum.finish()
    lams = wavelengths_nm if wavelengths_nm is not None else lams
    lams = [lams] if isinstance(lams, int | float) else lams
    if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in lams):
        raise ConfigError(f"spectrum.wavelengths_nm must be numbers (nm), got {lams!r}")
    with prefixed("spectrum.wavelengths_nm" if wavelengths_nm is None else "wavelengths"):
        check_wavelengths_nm(lams)
    if scale is not None and window is not None:
        raise ConfigError("give model.window_mm or output.pixel_scale_deg, not both")
    if pixel_scale_deg is not None:
        # An override (--pixel-scale-deg, a fitted photo's scale) sets the sampling, as it
        # does for every model kind: it replaces the window the config gives.
        scale, window = pixel_scale_deg, None
    return HolographicEye.build(
        eye,
        npix=out_npix if npix is None else npix,
        window_mm=8.0 if window is None and scale is None else window,
        pixel_scale_deg=scale,
        wavelengths_nm=tuple(float(v) for v in lams),
        **kwargs,
    )
