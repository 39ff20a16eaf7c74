"""Specs of synthetic target photos: which model, which observation, which noise draw.

A spec is a TOML file read by ``invglare synth``::

    [synth]
    model = "../examples/eye_daylight.toml"  # model config, relative to this spec
    seed = 1                  # noise draw (Poisson electrons and read noise)
    out = "eye_daylight"      # output name (default: the spec's stem), next to the spec
    pixel_type = "half"       # "half" (16-bit, default) or "float" (32-bit) EXR pixels

    [set]                     # optional: model values that differ from the model config
    "model.aperture.pupil.diameter_mm" = 2.8

    [observation]             # fields of invglare.fit.Observation
    flux = 3e7                # total source counts
    background = 20.0         # counts per pixel
    dx_px = 0.3               # source centre offset from pixel (W//2, H//2)
    dy_px = -0.2
    rotation_deg = 0.0
    pixel_scale_ratio = 1.0   # model pixel scale / photo pixel scale
    response = 1.0
    gain = 2.0                # electrons per count
    read_noise = 3.0          # counts rms
    saturation = 60000.0      # clip level (counts); omit for no clipping
    source_radius_px = 0.0    # omit for a point source

Instead of ``synth.model`` a spec may hold the model itself: ``[model]``,
``[output]`` and ``[spectrum]`` tables as in a model config
(:mod:`invglare.config.model`). The model must be monochrome (one
wavelength): a photo here is one channel of counts.

**Example:**

```python
spec = load_synth("data_synthetic/eye_daylight.toml")
spec.out_exr   # data_synthetic/eye_daylight.exr
```
"""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path
from typing import Any

from invglare.config.section import Section, check_sections
from invglare.errors import ConfigError, PhysicsRangeError
from invglare.files.toml import load_toml

#: Top-level tables of a synth spec.
SECTIONS = ("synth", "set", "observation", "model", "output", "spectrum", "population")
#: Observation fields a spec may give (see :class:`invglare.fit.Observation`).
OBSERVATION_KEYS = (
    "flux",
    "background",
    "dx_px",
    "dy_px",
    "rotation_deg",
    "pixel_scale_ratio",
    "response",
    "gain",
    "read_noise",
    "source_radius_px",
    "saturation",
)
PIXEL_TYPES = ("half", "float")
_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")


@dataclasses.dataclass(frozen=True)
class SynthSpec:
    """A parsed synth spec (see the module docstring).

    **Fields:**

    - `path`: the spec file.
    - `name`: output name; the photo is ``<dir>/<name>.exr``, the truth
      ``<dir>/<name>.truth.json``.
    - `model_config`: the model config table (read from `model_path` or inline).
    - `model_path`: the model config file, or None for an inline model.
    - `base_dir`: where relative paths in the model config are resolved.
    - `set_values`: ``{path: value}`` written into the built model (paths as in a fit,
      ``"model.…"``).
    - `observation`: ``{field: value}`` for :class:`invglare.fit.Observation`.
    - `seed`: the noise seed.
    - `pixel_type`: ``"half"`` or ``"float"``.
    - `out_dir`: the folder the outputs go to.
    - `drawn`: for a member of a population (:mod:`invglare.config.population`), the
      values drawn for it, ``{key: value}`` (empty otherwise).
    """

    path: Path
    name: str
    model_config: dict[str, Any]
    model_path: Path | None
    base_dir: Path
    set_values: dict[str, float]
    observation: dict[str, float | None]
    seed: int
    pixel_type: str
    out_dir: Path
    drawn: dict[str, Any] = dataclasses.field(default_factory=dict)

    @property
    def out_exr(self) -> Path:
        return self.out_dir / f"{self.name}.exr"

    @property
    def out_truth(self) -> Path:
        return self.out_dir / f"{self.name}.truth.json"


def truth_path_for(photo: str | Path) -> Path:
    """Where ``invglare synth`` puts the ground truth of a photo: ``NAME.truth.json`` beside it."""
    p = Path(photo)
    return p.with_name(f"{p.stem}.truth.json")


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(f"{where} must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise ConfigError(f"{where} must be finite, got {value!r}")
    return v


def read_observation(table: Any, where: str = "observation") -> dict[str, float | None]:
    """Check an ``[observation]`` table: known fields, finite numbers. **Returns:** a dict."""
    if not isinstance(table, dict):
        raise ConfigError(f"[{where}] must be a table, got {table!r}")
    out: dict[str, float | None] = {}
    for key, value in table.items():
        if key not in OBSERVATION_KEYS:
            raise ConfigError(
                f"[{where}] has unknown key {key!r}; valid keys: {', '.join(OBSERVATION_KEYS)}"
            )
        out[key] = _number(value, f"{where}.{key}")
    if out.get("flux") is not None and out["flux"] < 0:
        raise PhysicsRangeError(
            f"{where}.flux must be >= 0 counts (a source gives light), got {out['flux']:g}"
        )
    return out


def load_synth_specs(path: str | Path, out_dir: str | Path | None = None) -> list[SynthSpec]:
    """The photos a synth spec describes: itself, or each member of its ``[population]``.

    A population's members (see :mod:`invglare.config.population`) are named
    ``NAME_00``, ``NAME_01``, ... and go into the folder ``synth.out`` (default: the spec's
    stem) beside the spec (or in `out_dir`); member `i` has the noise seed
    ``synth.seed + i`` and its drawn values written into its model config, ``[set]`` and
    ``[observation]``.

    **Raises:** :class:`~invglare.errors.ConfigError` as :func:`load_synth` does, and for
    a bad ``[population]`` table or a drawn model-config key the model config lacks.
    """
    import copy

    from invglare.config.paths import get_key, set_key
    from invglare.config.population import member_values, read_population

    spec_path = Path(path)
    config = load_toml(spec_path)
    if "population" not in config:
        return [load_synth(spec_path, out_dir)]
    population = read_population(config["population"])
    base = _load(spec_path, {k: v for k, v in config.items() if k != "population"}, out_dir)
    folder = base.out_dir / base.name
    members = []
    for i, member in enumerate(population.draw()):
        model_config = copy.deepcopy(base.model_config)
        for key, value in member["config"].items():
            # The key's table must exist; the key itself may be new (a default made explicit).
            get_key(model_config, key.rsplit(".", 1)[0], f"population.config.{key!r}")
            set_key(model_config, key, value)
        members.append(
            dataclasses.replace(
                base,
                name=population.member_name(base.name, i),
                model_config=model_config,
                set_values={**base.set_values, **{k: float(v) for k, v in member["set"].items()}},
                observation={**base.observation, **member["observation"]},
                seed=base.seed + i,
                out_dir=folder,
                drawn=member_values(member),
            )
        )
        _check_observation(members[-1].observation)
    return members


def _check_observation(observation: dict[str, float | None]) -> None:
    """Every field's range, as the photo model checks it, before any model is built."""
    from invglare.errors import InvglareError
    from invglare.fit import Observation

    try:
        Observation(**observation)
    except InvglareError as err:
        raise type(err)(f"[observation]: {err}") from None


def load_synth(path: str | Path, out_dir: str | Path | None = None) -> SynthSpec:
    """Parse and check a synth spec; nothing is built or written.

    **Arguments:**

    - `path`: the spec (TOML).
    - `out_dir`: where the outputs go (default: the spec's folder).

    **Raises:** :class:`~invglare.errors.ConfigError` naming the key for a missing
    file, unknown tables or keys, values of the wrong type, a missing model, or a
    model given both ways.
    """
    spec_path = Path(path)
    config = load_toml(spec_path)
    if "population" in config:
        raise ConfigError(
            f"{spec_path} describes a population of photos ([population]); read it with "
            "load_synth_specs"
        )
    return _load(spec_path, config, out_dir)


def _load(spec_path: Path, config: dict[str, Any], out_dir: str | Path | None) -> SynthSpec:
    source = str(spec_path)
    check_sections(config, SECTIONS, source)
    synth = Section(config.get("synth", {}), "synth")
    model_ref = synth.get("model", str, None)
    seed = synth.get("seed", int, 0)
    name = synth.get("out", str, spec_path.stem)
    pixel_type = synth.choice("pixel_type", PIXEL_TYPES, "half")
    synth.finish()
    if not _NAME.match(name):
        raise ConfigError(
            f"synth.out = {name!r} must be a plain file name (letters, digits, '_', '-', '.')"
        )
    if seed < 0:
        raise ConfigError(f"synth.seed must be an integer >= 0, got {seed}")

    inline = {k: config[k] for k in ("model", "output", "spectrum") if k in config}
    if model_ref is not None:
        if inline:
            raise ConfigError(
                f"{source}: give the model either as synth.model = path or inline as [model], "
                f"not both (found synth.model and [{'], ['.join(inline)}])"
            )
        model_path = (spec_path.parent / model_ref).resolve()
        if not model_path.is_file():
            what = "is a folder, not a TOML file" if model_path.is_dir() else "does not exist"
            raise ConfigError(f"synth.model = {model_ref!r}: the model config {model_path} {what}")
        model_config = load_toml(model_path)
        base_dir = model_path.parent
    else:
        if "model" not in inline:
            raise ConfigError(
                f"{source}: no model; set synth.model = 'path/to/model.toml' or add a [model] table"
            )
        model_path, model_config, base_dir = None, inline, spec_path.parent

    set_table = config.get("set", {})
    if not isinstance(set_table, dict):
        raise ConfigError(f"[set] must be a table of path = value, got {set_table!r}")
    set_values = {}
    for key, value in set_table.items():
        if not key.startswith("model."):
            raise ConfigError(
                f"[set] key {key!r} must be a model path starting with 'model.' (e.g. "
                '"model.aperture.pupil.diameter_mm"); observation values go in [observation]'
            )
        set_values[key] = _number(value, f"set.{key!r}")

    observation = read_observation(config.get("observation", {}))
    if observation.get("background", 0.0) < 0:
        raise PhysicsRangeError(
            f"observation.background must be >= 0 counts per pixel (the mean of a photo's "
            f"counts cannot be negative), got {observation['background']:g}"
        )
    _check_observation(observation)
    return SynthSpec(
        path=spec_path,
        name=name,
        model_config=model_config,
        model_path=model_path,
        base_dir=base_dir,
        set_values=set_values,
        observation=observation,
        seed=seed,
        pixel_type=pixel_type,
        out_dir=Path(out_dir) if out_dir is not None else spec_path.parent,
    )
