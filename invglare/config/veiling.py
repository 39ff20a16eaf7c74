"""Veiling-glare models and lens prescriptions from TOML tables, and back.

**Model config** (the ``"veiling"`` kind of a model config; every key but
``kind`` and one of ``[model.ghosts]`` / ``[model.lens]`` has a default)::

    [model]
    kind = "veiling"
    profile = "disk"              # ghost shape: "disk", "hat" or "cosine"
    n_harmonics = 64              # N: highest harmonic on each axis
    sigma_strength = 1.0          # de-ringing exponent (0: off, 1: Lanczos)
    window = "lanczos"            # or "fejer"
    positivity = "clip"           # or "none"
    pixel_average = true
    quadrature_nodes = 48         # for profile = "cosine"
    period_factor = 2.0           # series period / larger screen side (sec. 4.1)
    light_angle_deg = [0.0, 0.0]  # the light's direction (x, y) when none is given

    [model.ghosts]                # free ghosts (what a fit adjusts) ...
    position_deg = [[0.0, 0.0], [1.5, -0.5]]
    radius_deg = [2.0, 3.5]       # a number applies to every ghost
    intensity_per_sr = [0.01, 0.004]
    softness_deg = 0.05
    ratio = [0.3, -0.8]           # motion with the light (0: fixed on the screen)
    transmission = 1.0            # share of the light in the direct image

    [model.lens]                  # ... or ghosts of a lens prescription
    file = "cooke_triplet"        # a bundled lens, or a TOML path relative to this config
    max_reflections = 2           # 2, 4, ...
    softness_deg = 0.05
    min_radius_deg = 0.05
    focus = false                 # true: move the sensor to the paraxial focus
    reflectance = 0.01            # optional: overrides the file's coating reflectance
    sensor_reflectance = 0.02     # optional: overrides the file's sensor reflectance

    [output]
    npix = 512                    # or [ny, nx]
    pixel_scale_deg = 0.05

Instead of ``file``, ``[model.lens]`` may hold a prescription itself (the keys of a
lens file below); a veiling model's ``to_config()`` writes lenses that way, so fitted
lens parameters survive the round trip.

**Lens file** (``invglare/data/lenses/*.toml``; :func:`load_lens_file`)::

    name = "Cooke triplet"
    source = "where the numbers come from"
    stated_effective_focal_length_mm = 101.181   # optional, for checks
    stated_back_focal_length_mm = 77.405         # optional
    stated_f_number = 3.5                        # optional
    reflectance = 0.01        # coating of every glass-air surface (default 0)
    sensor_reflectance = 0.02 # default 0 (no sensor ghosts)
    object_index = 1.0

    [[surfaces]]              # from the object side
    radius_mm = 37.40         # 0 for a flat surface
    thickness_mm = 5.90       # to the next vertex; the last one: to the sensor
    index = 1.61272           # refractive index after the surface
    semi_aperture_mm = 14.7
    glass = "SK4"             # optional label
    stop = true               # on exactly one surface
    reflectance = 0.005       # optional per-surface override

Cemented (glass-glass) surfaces get the uncoated Fresnel reflectance of their index
step unless a per-surface ``reflectance`` says otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from invglare._core.memory import check_psf_memory
from invglare.config.raster import KEEP_GRID, GridRequest
from invglare.config.section import Section
from invglare.errors import ConfigError, PhysicsRangeError
from invglare.files.toml import load_toml
from invglare.models.veiling import POSITIVITY, VeilingGlare
from invglare.models.veiling_ghosts import GhostSet, LensGhosts
from invglare.models.veiling_series import PROFILES, WINDOWS
from invglare.optics.paraxial import Lens

__all__ = [
    "BUNDLED_LENS_DIR",
    "LensFile",
    "bundled_lenses",
    "lens_from_table",
    "load_lens",
    "load_lens_file",
    "veiling_from_config",
]

#: Where the bundled lens prescriptions live.
BUNDLED_LENS_DIR = Path(__file__).resolve().parent.parent / "data" / "lenses"

# ------------------------------------------------------------------------------ lenses


@dataclass(frozen=True)
class LensFile:
    """A lens prescription with what its file says about it.

    `stated_*` are the source's own paraxial values (``None`` if not given), for checks.
    """

    lens: Lens
    name: str
    source: str
    stated_effective_focal_length_mm: float | None
    stated_back_focal_length_mm: float | None
    path: Path | None = None
    stated_f_number: float | None = None


def bundled_lenses() -> tuple[str, ...]:
    """Names of the bundled prescriptions (``load_lens(name)``)."""
    return tuple(sorted(p.stem for p in BUNDLED_LENS_DIR.glob("*.toml")))


def lens_from_table(table: dict[str, Any], where: str = "lens") -> LensFile:
    """A :class:`LensFile` from a lens table (the keys of a lens file; see the module doc).

    **Example:**

    ```python
    info = lens_from_table(tomllib.load(open("my_lens.toml", "rb")))
    info.lens.effective_focal_length_mm()
    ```
    """
    t = Section(table, where)
    name = t.get("name", (str,), "")
    source = t.get("source", (str,), "")
    efl = t.get("stated_effective_focal_length_mm", (float,), None)
    bfl = t.get("stated_back_focal_length_mm", (float,), None)
    f_number = t.get("stated_f_number", (float,), None)
    coating = t.get("reflectance", (float,), 0.0)
    sensor = t.get("sensor_reflectance", (float,), 0.0)
    object_index = t.get("object_index", (float,), 1.0)
    surfaces = t.get("surfaces", (list,))
    t.finish()
    if not surfaces:
        raise ConfigError(f"{where}.surfaces is empty; give at least one [[surfaces]] table")
    columns: dict[str, list[float]] = {
        k: [] for k in ("radius_mm", "thickness_mm", "index", "semi_aperture_mm")
    }
    stops, overrides = [], {}
    for i, surface in enumerate(surfaces):
        s = Section(surface, f"{where}.surfaces[{i}]")
        for key in columns:
            columns[key].append(s.get(key, (float,)))
        s.get("glass", (str,), "")
        if s.get("stop", (bool,), False):
            stops.append(i)
        r = s.get("reflectance", (float,), None)
        if r is not None:
            overrides[i] = r
        s.finish()
    if len(stops) != 1:
        raise ConfigError(
            f"{where}: exactly one surface must have stop = true, found {len(stops)}"
            + (f" (surfaces {stops})" if stops else "")
        )
    lens = Lens.from_radii(
        columns["radius_mm"],
        columns["thickness_mm"],
        columns["index"],
        columns["semi_aperture_mm"],
        stop_index=stops[0],
        reflectance=coating,
        sensor_reflectance=sensor,
        object_index=object_index,
        name=name,
    )
    if overrides:
        refl = np.asarray(lens.reflectance, dtype=float).copy()
        for i, r in overrides.items():
            refl[i] = r
        lens = Lens(
            curvature_per_mm=lens.curvature_per_mm,
            thickness_mm=lens.thickness_mm,
            index=lens.index,
            semi_aperture_mm=lens.semi_aperture_mm,
            reflectance=refl,
            sensor_reflectance=lens.sensor_reflectance,
            stop_index=lens.stop_index,
            object_index=lens.object_index,
            name=lens.name,
        )
    return LensFile(lens, name, source, efl, bfl, stated_f_number=f_number)


def _lens_path(name_or_path: str | Path, base_dir: str | Path | None) -> Path:
    text = str(name_or_path)
    if text in bundled_lenses():
        return BUNDLED_LENS_DIR / f"{text}.toml"
    path = Path(text)
    if not path.is_absolute() and base_dir is not None:
        path = Path(base_dir) / path
    if not path.is_file():
        raise ConfigError(
            f"lens {text!r} is neither a bundled lens ({', '.join(bundled_lenses())}) "
            f"nor an existing file"
        )
    return path



def load_lens_file(name_or_path: str | Path, base_dir: str | Path | None = None) -> LensFile:
    """Read a lens prescription: a bundled name (:func:`bundled_lenses`) or a TOML path.

    **Example:**

    ```python
    info = load_lens_file("double_gauss")
    info.stated_effective_focal_length_mm   # 100.4
    ```
    """
    path = _lens_path(name_or_path, base_dir)
    info = lens_from_table(load_toml(path), where=path.name)
    return LensFile(
        info.lens,
        info.name,
        info.source,
        info.stated_effective_focal_length_mm,
        info.stated_back_focal_length_mm,
        path,
        info.stated_f_number,
    )


def load_lens(name_or_path: str | Path, base_dir: str | Path | None = None) -> Lens:
    """The :class:`~invglare.optics.paraxial.Lens` of :func:`load_lens_file`.

    **Example:**

    ```python
    lens = load_lens("cooke_triplet")
    ```
    """
    return load_lens_file(name_or_path, base_dir).lens



# ------------------------------------------------------------------------------ model

_LENS_MODEL_KEYS = ("max_reflections", "softness_deg", "min_radius_deg", "focus", "file")


def _ghosts_from_table(table: dict[str, Any]) -> GhostSet:
    t = Section(table, "model.ghosts")
    position = t.numbers("position_deg", shape="a list of [x, y] pairs")
    radius = t.numbers("radius_deg")
    intensity = t.numbers("intensity_per_sr")
    softness = t.numbers("softness_deg", 0.0)
    ratio = t.numbers("ratio", 0.0)
    transmission = t.get("transmission", (float,), 1.0)
    t.finish()
    if position.ndim != 2 or position.shape[1] != 2 or position.shape[0] == 0:
        raise ConfigError(
            f"model.ghosts.position_deg must be a non-empty list of [x, y] pairs, "
            f"got shape {position.shape}"
        )
    try:
        return GhostSet.build(position, radius, intensity, softness, ratio, transmission)
    except PhysicsRangeError as err:
        raise PhysicsRangeError(f"model.ghosts: {err}") from err


def _lens_ghosts_from_table(table: dict[str, Any], base_dir: str | Path | None) -> LensGhosts:
    t = Section(table, "model.lens")
    max_reflections = t.get("max_reflections", (int,), 2)
    softness = t.get("softness_deg", (float,), 0.05)
    min_radius = t.get("min_radius_deg", (float,), 0.05)
    focus = t.get("focus", (bool,), False)
    file = t.get("file", (str,), None)
    lens_keys = {k: v for k, v in table.items() if k not in _LENS_MODEL_KEYS}
    if file is not None:
        path = _lens_path(file, base_dir)
        extra = set(lens_keys) - {"reflectance", "sensor_reflectance"}
        if extra:
            raise ConfigError(
                f"[model.lens] with a file takes only reflectance and sensor_reflectance "
                f"as overrides, got {sorted(extra)[0]!r}"
            )
        lens_table = {**load_toml(path), **lens_keys}
        where = f"{path.name} (with model.lens overrides)" if lens_keys else path.name
    else:
        if "surfaces" not in lens_keys:
            raise ConfigError(
                "[model.lens] needs a lens: a 'file' or inline [[model.lens.surfaces]]"
            )
        lens_table, where = lens_keys, "model.lens"
    t.accept(lens_keys)
    t.finish()
    lens = lens_from_table(lens_table, where).lens
    if focus:
        lens = lens.focused()
    return LensGhosts.build(
        lens, max_reflections=max_reflections, softness_deg=softness, min_radius_deg=min_radius
    )


def veiling_from_config(
    config: dict[str, Any],
    base_dir: str | Path | None = None,
    grid: GridRequest = KEEP_GRID,
    source: str = "config",
) -> VeilingGlare:
    """Build a :class:`~invglare.models.veiling.VeilingGlare` from a model config.

    **Arguments:**

    - `config`: the whole parsed TOML (sections ``[model]`` with ``kind = "veiling"``
      and optionally ``[output]``; see the module docstring).
    - `base_dir`: directory that relative lens paths are resolved against.
    - `grid`: its `npix` and `pixel_scale_deg` override ``[output]``; its
      `wavelengths_nm` must be ``None``: the veiling model is monochrome.
    - `source`: name of the config in error messages.

    **Raises:** `ConfigError` for unknown keys or sections, wrong types, a
    ``[spectrum]`` section or wavelengths; `PhysicsRangeError` for impossible values.

    **Example:**

    ```python
    model = veiling_from_config(tomllib.load(open("examples/veiling_cooke.toml", "rb")),
                                base_dir="examples")
    ```
    """
    for section in config:
        if section not in ("model", "output"):
            hint = " (the veiling model is monochrome)" if section == "spectrum" else ""
            raise ConfigError(
                f"{source}: section [{section}] does not apply to a veiling model{hint}; "
                "valid sections: model, output"
            )
    if grid.wavelengths_nm is not None:
        raise ConfigError("the veiling model is monochrome; wavelengths do not apply to it")
    if "model" not in config:
        raise ConfigError(f"{source}: no [model] section")
    m = Section(config["model"], "model")
    kind = m.get("kind", (str,))
    if kind != "veiling":
        raise ConfigError(f"model.kind = {kind!r}; veiling_from_config reads kind = 'veiling'")
    options = dict(
        profile=m.choice("profile", PROFILES, "disk"),
        n_harmonics=m.get("n_harmonics", (int,), 64),
        sigma_strength=m.get("sigma_strength", (float,), 1.0),
        window=m.choice("window", WINDOWS, "lanczos"),
        positivity=m.choice("positivity", POSITIVITY, "clip"),
        pixel_average=m.get("pixel_average", (bool,), True),
        quadrature_nodes=m.get("quadrature_nodes", (int,), 48),
        period_factor=m.get("period_factor", (float,), 2.0),
        light_angle_deg=m.numbers("light_angle_deg", (0.0, 0.0), shape="a pair [x, y] of angles"),
    )
    ghost_table = m.get("ghosts", (dict,), None)
    lens_table = m.get("lens", (dict,), None)
    m.finish()
    if (ghost_table is None) == (lens_table is None):
        raise ConfigError(
            f"{source}: a veiling model needs exactly one of [model.ghosts] and [model.lens]"
        )
    ghosts = (
        _ghosts_from_table(ghost_table)
        if ghost_table is not None
        else _lens_ghosts_from_table(lens_table, base_dir)
    )
    out = Section(config.get("output", {}), "output")
    shape = out.get("npix", (int, list), 512)
    scale = out.get("pixel_scale_deg", (float,), 0.05)
    out.finish()
    if isinstance(shape, list):
        if len(shape) != 2 or not all(
            isinstance(v, int) and not isinstance(v, bool) for v in shape
        ):
            raise ConfigError(f"output.npix must be an integer or [ny, nx], got {shape!r}")
        shape = (shape[0], shape[1])
    shape = shape if grid.npix is None else grid.npix
    if isinstance(shape, int) or all(isinstance(v, int) and v > 0 for v in shape):
        check_psf_memory(source, aperture_npix=None, npix=shape, n_wavelengths=1,
                         names="output.npix")  # fmt: skip
    return VeilingGlare.build(
        ghosts,
        npix=shape,
        pixel_scale_deg=scale if grid.pixel_scale_deg is None else grid.pixel_scale_deg,
        **options,
    )
