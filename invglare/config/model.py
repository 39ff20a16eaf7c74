"""Model configs: `model.kind` → the model's class and its config reader, in one registry.

A model config is a TOML file with a ``[model]`` table whose ``kind`` names a registered
model kind, and the tables that kind reads (usually ``[output]`` and ``[spectrum]``):

| kind        | model                                                  | reader                    |
|-------------|--------------------------------------------------------|---------------------------|
| `aperture`  | :class:`~invglare.models.aperture_psf.AperturePSF`     | `config.raster`           |
| `eye`       | :class:`~invglare.models.kakimoto.KakimotoGlare`       | `config.raster`           |
| `camera`    | :class:`~invglare.models.kakimoto.KakimotoGlare`       | `config.raster`           |
| `veiling`   | :class:`~invglare.models.veiling.VeilingGlare`         | `config.veiling`          |
| `temporal`  | :class:`~invglare.models.temporal.TemporalGlare`       | `config.temporal`         |
| `holographic` | :class:`~invglare.models.holographic.HolographicEye` | `config.holographic`      |

:func:`build_model` reads a config through its kind's reader; a built model writes its
config back with ``model.to_config()``. Adding a kind is its model file in
``invglare/models/``, its reader, and one :func:`register_model_kind` line (below, or in
your own code for a kind of your own; see ``CONTRIBUTING.md``).

**Example:**

```python
from invglare.config.model import build_model
from invglare.files.toml import load_toml

model = build_model(load_toml("examples/eye_daylight.toml"), base_dir="examples")
psf = model()                                   # on-axis PSF
again = build_model(model.to_config())          # the same model
```
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

from invglare.config.holographic import holographic_from_config
from invglare.config.raster import GridRequest, read_raster_model
from invglare.config.section import Section
from invglare.config.temporal import temporal_from_config
from invglare.config.veiling import veiling_from_config
from invglare.errors import ConfigError
from invglare.fit.ghost_report import ghost_report_sections
from invglare.models.aperture_psf import AperturePSF
from invglare.models.base import AbstractGlareModel
from invglare.models.holographic import HolographicEye
from invglare.models.kakimoto import KakimotoGlare
from invglare.models.temporal import TemporalGlare
from invglare.models.veiling import VeilingGlare

#: A kind's config reader: ``read(config, base_dir, grid, source) -> model``, the parsed
#: TOML, where its relative paths are resolved, what the caller asks of the grid
#: (:class:`~invglare.config.raster.GridRequest`) and the config's name for messages.
ModelReader = Callable[[dict[str, Any], Any, GridRequest, str], AbstractGlareModel]


@dataclasses.dataclass(frozen=True)
class ModelKind:
    """A registered model kind: its name, its model class and its config reader."""

    name: str
    model_class: type[AbstractGlareModel]
    read: ModelReader
    #: Report sections particular to the kind: ``report(fitted, truth) -> {key: (title,
    #: lines, data)}`` for a fit's ``report.md`` and ``params.json`` (truth: the true model
    #: or None).
    report: Callable[[Any, Any], dict[str, tuple[str, list[str], Any]]] | None = None


_KINDS: dict[str, ModelKind] = {}


def register_model_kind(
    name: str,
    model_class: type[AbstractGlareModel],
    read: ModelReader,
    report: Callable[[Any, Any], dict[str, tuple[str, list[str], Any]]] | None = None,
) -> ModelKind:
    """Register `model.kind = name`: configs of that kind are read by `read` into a
    `model_class`; `report` (optional) adds a section to the reports of its fits.

    **Raises:** `ConfigError` for a name already taken by another class, or a class that
    does not implement :class:`~invglare.models.base.AbstractGlareModel`.

    **Example:**

    ```python
    register_model_kind("toy", ToyGlare, read_toy)
    model = build_model({"model": {"kind": "toy", "width_deg": 0.1}})
    ```
    """
    if not isinstance(model_class, type) or not issubclass(model_class, AbstractGlareModel):
        raise ConfigError(
            f"model kind {name!r}: {model_class!r} does not implement AbstractGlareModel"
        )
    known = _KINDS.get(name)
    if known is not None and known.model_class is not model_class:
        raise ConfigError(
            f"model kind {name!r} is taken by {known.model_class.__name__}; choose another name"
        )
    kind = ModelKind(name, model_class, read, report)
    _KINDS[name] = kind
    return kind


def model_kinds() -> tuple[str, ...]:
    """The registered kind names, in registration order."""
    return tuple(_KINDS)


def model_kind(name: Any) -> ModelKind:
    """The registered kind `name`, or a ConfigError listing the valid ones."""
    if name not in _KINDS:
        raise ConfigError(
            f"model.kind = {name!r} is unknown; valid kinds: {', '.join(model_kinds())}"
        )
    return _KINDS[name]


def config_kind(config: dict[str, Any], source: str = "config") -> ModelKind:
    """The registered kind a parsed model config names (checked, before any building)."""
    if not isinstance(config, dict) or "model" not in config:
        raise ConfigError(f"{source}: no [model] section")
    table = Section(config["model"], "model")
    return model_kind(table.get("kind", str, required=True))


def kind_of(model: AbstractGlareModel) -> ModelKind:
    """The registered kind of a built model (the first registered for its class)."""
    for kind in _KINDS.values():
        if type(model) is kind.model_class:
            return kind
    raise ConfigError(f"{type(model).__name__} is not a registered model kind")


def build_model(
    config: dict[str, Any],
    base_dir: str | Path | None = None,
    *,
    npix: int | tuple[int, int] | None = None,
    pixel_scale_deg: float | None = None,
    wavelengths_nm: Any = None,
    source: str = "config",
) -> AbstractGlareModel:
    """Build the model a config describes; keyword arguments override its grid.

    **Arguments:**

    - `config`: the parsed TOML (``{"model": {...}, "output": {...}, ...}``).
    - `base_dir`: where relative paths in it (image masks, lens files) are resolved.
    - `npix`, `pixel_scale_deg`, `wavelengths_nm`: overrides of the output grid and the
      wavelengths (a fit builds the model on its photo's grid); `npix` may be
      ``(ny, nx)``.
    - `source`: where the config came from, for error messages.

    **Raises:** `ConfigError` for an unknown kind (listing the registered ones) and
    whatever the kind's reader raises for its keys.
    """
    kind = config_kind(config, source)
    return kind.read(config, base_dir, GridRequest(npix, pixel_scale_deg, wavelengths_nm), source)


# The built-in kinds: one line each.
register_model_kind("aperture", AperturePSF, read_raster_model)
register_model_kind("eye", KakimotoGlare, read_raster_model)
register_model_kind("camera", KakimotoGlare, read_raster_model)
register_model_kind("veiling", VeilingGlare, veiling_from_config, report=ghost_report_sections)
register_model_kind("temporal", TemporalGlare, temporal_from_config)
register_model_kind("holographic", HolographicEye, holographic_from_config)
