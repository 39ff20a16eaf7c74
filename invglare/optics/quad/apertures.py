"""The four apertures of the paper's experiments (sec. 5, fig. 8): box, circle, heptagon, whirl.

Each is 4 mm across (its circumscribed circle) on a window of ``npix`` pixels with two
empty pixels on each side, as a soft raster (anti-aliased coverage) and as an outline for
the exact polygon transform. The box, circle and heptagon are invglare shapes
(`RegularPolygon` with 4 sides turned by 45 degrees, `Disk`, `RegularPolygon` with 7);
the *whirl* is defined here: an iris of 9 curved blades whose edges make a pinwheel, the
opening's radius growing along each blade as ``R (0.78 + 0.22 u^2)`` (``u`` from 0 to 1
across the blade's 40 degrees) and dropping back at the next blade's tip. Its raster is the
area coverage estimated by 8 x 8 samples per pixel (a pixel's value is quantised to 1/64;
the figures and counts do not need more).
"""

from __future__ import annotations

import math

import numpy as np

from invglare._core.grids import ApertureGrid
from invglare.aperture import Aperture, Disk, RegularPolygon
from invglare.errors import ConfigError

#: The paper's apertures, in its order.
PAPER_APERTURES = ("box", "circle", "heptagon", "whirl")
#: Their circumscribed diameter (mm).
DIAMETER_MM = 4.0
WHIRL_BLADES = 9
_WHIRL_INNER = 0.78


def paper_grid(npix: int) -> ApertureGrid:
    """The window of `npix` pixels holding a 4 mm aperture with 2 empty pixels each side."""
    return ApertureGrid.from_width(npix, DIAMETER_MM * npix / (npix - 4))


def paper_shape(name: str):
    """The invglare shape of the box, circle or heptagon (None for the whirl)."""
    if name == "box":
        return RegularPolygon(4, DIAMETER_MM, rotation_deg=45.0)
    if name == "circle":
        return Disk(DIAMETER_MM)
    if name == "heptagon":
        return RegularPolygon(7, DIAMETER_MM)
    if name == "whirl":
        return None
    raise ConfigError(f"aperture {name!r} is not one of {', '.join(PAPER_APERTURES)}")


def whirl_radius(theta: np.ndarray) -> np.ndarray:
    """The whirl's radius (mm) at polar angle `theta` (rad)."""
    u = np.mod(theta * WHIRL_BLADES / (2.0 * math.pi), 1.0)
    return 0.5 * DIAMETER_MM * (_WHIRL_INNER + (1.0 - _WHIRL_INNER) * u * u)


def whirl_outline(points_per_blade: int = 64) -> np.ndarray:
    """Counter-clockwise vertices (mm) of the whirl: each blade's curve, then its tip."""
    verts = []
    for k in range(WHIRL_BLADES):
        u = np.arange(points_per_blade + 1) / points_per_blade
        u[-1] = 1.0 - 1e-9  # the tip, just before the radius drops back
        theta = (k + u) * 2.0 * math.pi / WHIRL_BLADES
        r = whirl_radius(theta)
        verts.append(np.stack([r * np.cos(theta), r * np.sin(theta)], -1))
    return np.concatenate(verts)


def _whirl_raster(grid: ApertureGrid, samples: int = 8) -> np.ndarray:
    n = grid.npix
    pitch = float(grid.pitch_mm)
    offsets = (np.arange(samples) + 0.5) / samples - 0.5
    coords = (np.arange(n) - n // 2) * pitch
    out = np.zeros((n, n))
    for oy in offsets:  # one sub-row of samples at a time keeps memory at one raster
        y = (coords + oy * pitch)[:, None]
        for ox in offsets:
            x = (coords + ox * pitch)[None, :]
            out += np.hypot(x, y) < whirl_radius(np.arctan2(y, x))
    return out / samples**2


def paper_raster(name: str, npix: int) -> np.ndarray:
    """The soft raster (float64) of one of :data:`PAPER_APERTURES` on :func:`paper_grid`."""
    grid = paper_grid(npix)
    shape = paper_shape(name)
    if shape is None:
        return _whirl_raster(grid)
    return np.asarray(Aperture((shape,)).transmission(grid), dtype=np.float64)


def paper_outline(name: str) -> np.ndarray:
    """The outline vertices (mm, counter-clockwise) of a polygonal paper aperture."""
    if name == "whirl":
        return whirl_outline()
    shape = paper_shape(name)
    if isinstance(shape, RegularPolygon):
        n = shape.n_blades
        angle = math.radians(float(shape.rotation_deg)) + 2.0 * math.pi * np.arange(n) / n
        r = 0.5 * float(shape.diameter_mm)
        return np.stack([r * np.cos(angle), r * np.sin(angle)], -1)
    raise ConfigError(f"aperture {name!r} is not a polygon (the circle is an exact ellipse)")
