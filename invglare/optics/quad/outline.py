"""invglare's analytic shapes as exactly transformable pieces: polygons and ellipses.

| shape | piece | exact? |
|---|---|---|
| `Disk`, `Ellipse` | ellipse | yes (``jinc``) |
| `RegularPolygon`, rounding 0 | its `n` vertices | yes |
| `RegularPolygon`, rounding > 0 | each arc as `arc_segments` chords | inscribed chords |
| `Capsule` | a stadium: two sides, each round end as `arc_segments` chords | chords inscribed |
| `ImageMask` | refused: it has no geometry (use the quad method) | - |

Every vertex is a JAX function of the shape's parameters, so transforms are differentiable
in them. An inscribed chord of a circle of radius ``r`` subtending ``2 phi`` misses
``r^2 (phi - sin(phi) cos(phi)) ~ (2/3) r^2 phi^3`` of area: with 16 chords per
half-circle, 0.6 % of a lash's round ends.

**How shapes combine.** :class:`~invglare.aperture.Aperture` unites its open shapes and
multiplies by its blocking ones. Transforms add, so ``F[open] - F[block]`` is exact where
the shapes do not overlap (a block inside the opening: Babinet). Where they do (two open
shapes, or a block reaching beyond the opening), what the sum gets wrong is exactly the
raster ``t - sum(open) + sum(block)`` of the soft coverages, which is zero except in the
overlaps; :class:`~invglare.optics.propagator.PolygonFraunhofer` transforms that residue by
quads (only the overlaps are rasterised).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax.numpy as jnp
from jaxtyping import Array, Float

from invglare._core.checks import is_concrete
from invglare.aperture import Aperture, Capsule, Disk, Ellipse, ImageMask, RegularPolygon
from invglare.errors import ConfigError

#: Chords per arc (rounded polygon edge, capsule end) by default.
ARC_SEGMENTS = 16


class Piece(NamedTuple):
    """One transformable piece: ``kind`` "polygon" (``vertices``, counter-clockwise) or
    "ellipse" (``centre``, ``semi_axes``, ``rotation_rad``), added with ``sign``."""

    kind: str
    sign: float
    vertices: Array | None = None
    centre: Array | None = None
    semi_axes: Array | None = None
    rotation_rad: Array | None = None


def _rounded_polygon(shape: RegularPolygon, arc_segments: int) -> Float[Array, "v 2"]:
    n = shape.n_blades
    radius = 0.5 * shape.diameter_mm
    apothem = radius * math.cos(math.pi / n)
    half_edge = radius * math.sin(math.pi / n)
    sagitta = shape.rounding * (radius - apothem)
    phi = jnp.deg2rad(shape.rotation_deg) + (2.0 * jnp.arange(n) + 1.0) * (math.pi / n)
    # Points along each edge from its first corner (v = -w) to just before the next one.
    v = half_edge * (2.0 * jnp.arange(arc_segments) / arc_segments - 1.0)
    m = half_edge * half_edge + sagitta * sagitta
    # Height of the arc above the chord at v, finite at sagitta 0 (a straight edge).
    root = jnp.sqrt(jnp.maximum(m * m - 4.0 * sagitta * sagitta * v * v, 0.0))
    u = apothem + sagitta - 2.0 * sagitta * v * v / (m + root)
    c, s = jnp.cos(phi)[:, None], jnp.sin(phi)[:, None]
    x = shape.center_mm[0] + c * u - s * v
    y = shape.center_mm[1] + s * u + c * v
    return jnp.stack([x.reshape(-1), y.reshape(-1)], axis=-1)


def _regular_polygon(shape: RegularPolygon) -> Float[Array, "v 2"]:
    angle = jnp.deg2rad(shape.rotation_deg) + 2.0 * math.pi * jnp.arange(shape.n_blades) / (
        shape.n_blades
    )
    r = 0.5 * shape.diameter_mm
    return jnp.stack(
        [shape.center_mm[0] + r * jnp.cos(angle), shape.center_mm[1] + r * jnp.sin(angle)], -1
    )


def _stadium(shape: Capsule, arc_segments: int) -> Float[Array, "v 2"]:
    a, b = shape.start_mm, shape.end_mm
    d = b - a
    length2 = jnp.sum(d * d)
    safe = length2 > 0.0
    d = jnp.where(safe, d / jnp.sqrt(jnp.where(safe, length2, 1.0)), jnp.array([1.0, 0.0]))
    base = jnp.arctan2(d[1], d[0])
    r = 0.5 * shape.thickness_mm
    # Half-circle around the end (from -normal through +d to +normal), then around the start.
    t = jnp.arange(arc_segments + 1) * (math.pi / arc_segments) - 0.5 * math.pi
    end_arc = b + r * jnp.stack([jnp.cos(base + t), jnp.sin(base + t)], -1)
    start_arc = a + r * jnp.stack([jnp.cos(base + t + math.pi), jnp.sin(base + t + math.pi)], -1)
    return jnp.concatenate([end_arc, start_arc], axis=0)


def shape_pieces(shape, arc_segments: int = ARC_SEGMENTS) -> Piece:
    """The transformable piece of one shape (sign +1 for ``"open"``, -1 for ``"block"``)."""
    sign = 1.0 if shape.role == "open" else -1.0
    if isinstance(shape, Disk):
        r = 0.5 * shape.diameter_mm
        return Piece("ellipse", sign, None, shape.center_mm, jnp.stack([r, r]), 0.0 * r)
    if isinstance(shape, Ellipse):
        a = 0.5 * shape.diameter_mm
        axes = jnp.stack([a, a * (1.0 - shape.ellipticity)])
        return Piece("ellipse", sign, None, shape.center_mm, axes, jnp.deg2rad(shape.rotation_deg))
    if isinstance(shape, RegularPolygon):
        rounded = not (_is_zero(shape.rounding))
        verts = _rounded_polygon(shape, arc_segments) if rounded else _regular_polygon(shape)
        return Piece("polygon", sign, verts)
    if isinstance(shape, Capsule):
        return Piece("polygon", sign, _stadium(shape, arc_segments))
    if isinstance(shape, ImageMask):
        raise ConfigError(
            "an image shape has no vertices for method = 'polygon'; use method = 'quad' "
            "(its raster's quads) or 'mft'"
        )
    raise ConfigError(f"method = 'polygon' cannot transform a {type(shape).__name__} shape")


def _is_zero(value) -> bool:
    """Whether a rounding is zero now: a traced one keeps its arcs (straight at 0, exact)."""
    return is_concrete(value) and float(value) == 0.0


def aperture_pieces(aperture: Aperture, window_mm, arc_segments: int = ARC_SEGMENTS) -> list[Piece]:
    """The pieces of an aperture; without an open shape, the square window is the opening."""
    pieces = [shape_pieces(s, arc_segments) for s in aperture.shapes]
    if not any(s.role == "open" for s in aperture.shapes):
        h = 0.5 * jnp.asarray(window_mm)
        square = jnp.stack([jnp.stack([-h, -h]), jnp.stack([h, -h]), jnp.stack([h, h]),
                            jnp.stack([-h, h])])  # fmt: skip
        pieces.insert(0, Piece("polygon", 1.0, square))
    return pieces
