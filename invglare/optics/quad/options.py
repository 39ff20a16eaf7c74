"""The choices of the quad and polygon propagation methods, validated once.

They are the ``[model.quad]`` and ``[model.polygon]`` tables of a model config
(:mod:`invglare.config.raster`), and static fields of the propagators.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from invglare._core.grids import AngularGrid, ApertureGrid
from invglare.errors import ConfigError, PhysicsRangeError
from invglare.optics.quad.outline import ARC_SEGMENTS

SYMMETRIES = ("auto", "none")

#: Phase error (rad) a quad's plane wave may reach before a sampling is unrepresentable.
_PHASE_BUDGET_RAD = 1e-3
#: Absolute error the Fresnel integrals may reach (their values are of order 1).
_FRESNEL_BUDGET = 1e-5


def _check_int(name: str, value, lo: int, hi: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise ConfigError(f"{name} must be an integer, got {value!r}")
    if value < lo or (hi is not None and value > hi):
        span = f">= {lo}" if hi is None else f"in {lo}..{hi}"
        raise PhysicsRangeError(f"{name} must be {span}, got {value}")
    return int(value)


def _from_table(cls, method: str, table: Mapping[str, Any] | None):
    """A method's options from its config table, naming an unknown key and the valid ones."""
    table = dict(table or {})
    names = [f.name for f in dataclasses.fields(cls)]
    unknown = [k for k in table if k not in names]
    if unknown:
        raise ConfigError(
            f"{method} option {unknown[0]!r} is unknown; valid options: {', '.join(names)}"
        )
    return cls(**table)


@dataclasses.dataclass(frozen=True)
class QuadOptions:
    """How a raster becomes quads and how they are evaluated.

    - `base_level`: 0 builds the quadtree from pixels (exact); 1 from 2x2 means (the
      paper's half-size start), 2 from 4x4 means (its aggressive quarter size).
    - `band`: fractional pixels and those within `band` pixels of them stay single quads
      (their gradients are exact; a fit may move edges that far); -1: merge by value only.
    - `symmetry`: ``"auto"`` skips the odd parts of an aperture symmetric about an axis
      (detected on the raster), ``"none"`` evaluates everything.
    - `cull_below`: skip output tiles whose intensity bound is below this fraction of the
      peak (0: no culling; sec. 4.3). An approximation of at most about that size per pixel.
    - `tile`: the culling tile (output pixels a side).
    """

    base_level: int = 0
    band: int = 0
    symmetry: str = "auto"
    cull_below: float = 0.0
    tile: int = 8

    def __post_init__(self):
        _check_int("quad base_level", self.base_level, 0, 4)
        _check_int("quad band", self.band, -1)
        if self.symmetry not in SYMMETRIES:
            raise ConfigError(f"quad symmetry = {self.symmetry!r} is not one of {SYMMETRIES}")
        value = self.cull_below
        if (
            isinstance(value, bool)
            or not isinstance(value, int | float)
            or not (0.0 <= value < 1.0)
        ):
            raise PhysicsRangeError(f"quad cull_below must be in [0, 1), got {value!r}")
        _check_int("quad tile", self.tile, 2, 256)

    @property
    def band_or_none(self) -> int | None:
        return None if self.band < 0 else self.band

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_mapping(cls, table: Mapping[str, Any] | None) -> QuadOptions:
        return _from_table(cls, "quad", table)


@dataclasses.dataclass(frozen=True)
class PolygonOptions:
    """How shapes become polygons: `arc_segments` chords per arc (rounded blade, capsule
    end), and the `band` of the overlap residue's quads (see :mod:`.outline`)."""

    arc_segments: int = ARC_SEGMENTS
    band: int = 2

    def __post_init__(self):
        _check_int("polygon arc_segments", self.arc_segments, 2, 4096)
        _check_int("polygon band", self.band, 0)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_mapping(cls, table: Mapping[str, Any] | None) -> PolygonOptions:
        return _from_table(cls, "polygon", table)


def step_px(grid: ApertureGrid, output: AngularGrid, wavelength_nm) -> Array:
    """The output pixel in cycles per raster pixel, ``dtheta * pitch / lambda``."""
    return output.pixel_scale_rad * grid.pitch_mm / (jnp.asarray(wavelength_nm) * 1e-6)


def check_representable(
    grid: ApertureGrid,
    output: AngularGrid,
    shortest_wavelength_nm: float,
    focal_length_mm: float | None = None,
) -> None:
    """Refuse a sampling whose closed-form phases the float type cannot carry.

    A quad's phase ``2 pi f c`` reaches ``2 pi * cycles`` at the output's edge for a quad at
    the window's edge; float32 keeps it to ``eps * 2 pi * cycles`` rad, refused beyond
    :data:`_PHASE_BUDGET_RAD`. In the near field the Fresnel integrals at ``s`` carry the
    phase ``pi s^2 / 2`` on a tail of size ``1 / (pi s)``: an absolute error ``eps s / 2``,
    refused beyond :data:`_FRESNEL_BUDGET`. The message names the way out (float64 through
    ``jax_enable_x64``, a smaller field).
    """
    eps = float(np.finfo(np.float64 if jax.config.jax_enable_x64 else np.float32).eps)
    f_max = math.radians(float(output.half_field_deg)) / (shortest_wavelength_nm * 1e-6)
    half_window = 0.5 * math.sqrt(2.0) * float(grid.width_mm)
    cycles = f_max * half_window
    worst = 2.0 * math.pi * cycles * eps
    what = f"phases reach {worst / eps:.3g} rad at the output's edge ({cycles:.4g} cycles"
    what += " across the window)"
    budget, unit = _PHASE_BUDGET_RAD, " rad"
    if focal_length_mm is not None:
        lam_d = shortest_wavelength_nm * 1e-6 * focal_length_mm
        s_max = math.sqrt(2.0 / lam_d) * (half_window + f_max * lam_d)
        if 0.5 * s_max * eps / _FRESNEL_BUDGET > worst / budget:
            worst, budget, unit = 0.5 * s_max * eps, _FRESNEL_BUDGET, ""
            what = f"Fresnel integrals reach the argument {s_max:.4g}"
    if worst > budget:
        precision = "float64" if eps < 1e-10 else "float32"
        raise PhysicsRangeError(
            f"this sampling cannot be represented in {precision}: the closed-form {what}, "
            f"which {precision} keeps only to {worst:.2g}{unit}; lower npix or "
            "pixel_scale_deg" + ("" if eps < 1e-10 else ", or enable float64 (jax_enable_x64)")
        )
