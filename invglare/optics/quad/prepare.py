"""What the quad and polygon propagators decide once, on concrete values, before any call.

The quadtree and its plan (mirrors, culled tiles) for a raster; the polygon pieces' small-
frequency points and the overlap residue's quads for an aperture. Calls then run a pure
JAX function of the raster (or the shapes) and check, cheaply, that what they are given
is still what was decided on (:func:`checked_raster`).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Complex, Float

from invglare._core.checks import is_concrete
from invglare._core.grids import AngularGrid, ApertureGrid
from invglare.aperture import Aperture
from invglare.errors import ConfigError, InputDataError
from invglare.optics.quad.cull import cull_tiles
from invglare.optics.quad.farfield import far_field_terms, plan_amplitudes
from invglare.optics.quad.options import PolygonOptions, QuadOptions
from invglare.optics.quad.outline import Piece, aperture_pieces
from invglare.optics.quad.plan import QuadPlan, detect_mirrors, make_plan
from invglare.optics.quad.polygon import ellipse_transform, polygon_transform, series_points
from invglare.optics.quad.quadtree import build_quadtree
from invglare.optics.quad.transform import Kernel, Tiles

#: A raster may depart from the one its quads were decided on by this much (of its peak).
DEPARTURE_TOLERANCE = 1e-5


def concrete_raster(field, method: str) -> np.ndarray:
    """The raster as numpy, refusing traced, complex or empty fields with the reason."""
    if not is_concrete(field):
        raise ConfigError(
            f"method = {method!r} decides its quadtree on a concrete raster, and this one is "
            "traced (inside jit, vmap or grad): prepare the propagator first with "
            "propagator.prepared(raster) (the models do so when they are built)"
        )
    arr = np.asarray(field)
    if np.iscomplexobj(arr):
        raise InputDataError(
            f"method = {method!r} transforms real transmissions; this field is complex "
            "(use method = 'mft' for a complex field)"
        )
    return arr


def quad_plan(raster: np.ndarray, options: QuadOptions) -> QuadPlan:
    """The quadtree of `raster` and its plan, with the raster's mirrors if asked."""
    layout = build_quadtree(raster, base_level=options.base_level, band=options.band_or_none)
    mirrors = detect_mirrors(raster) if options.symmetry == "auto" else (False, False)
    return make_plan(layout, *mirrors)


def quad_tiles(
    plan: QuadPlan,
    raster: np.ndarray,
    options: QuadOptions,
    kernel: Kernel,
    npix: int,
    steps: tuple[float, ...],
    params: tuple,
    far: bool,
) -> tuple | None:
    """The culled tiles (hashable) for the given evaluations, or None (no culling)."""
    if options.cull_below <= 0:
        return None
    amps, _ = plan_amplitudes(plan, jnp.asarray(raster))
    tiles = cull_tiles(
        plan, kernel, np.asarray(amps), steps, npix, options.cull_below,
        far=far, params=params, tile=options.tile,
    )  # fmt: skip
    if tiles is None:
        return None
    # Python ints: numpy (and JAX) scalars in a static field are arrays to equinox, which warns.
    return (tiles.size, tuple(map(int, tiles.rows)), tuple(map(int, tiles.cols)))


def as_tiles(tiles: tuple | None) -> Tiles | None:
    if tiles is None:
        return None
    size, rows, cols = tiles
    return Tiles(size, np.asarray(rows, int), np.asarray(cols, int))


def checked_raster(plan: QuadPlan, field: Float[Array, "n n"], method: str) -> Array:
    """`field`, with a runtime error if it departs from what its quads represent."""
    if jnp.iscomplexobj(field):
        raise InputDataError(f"method = {method!r} transforms real transmissions, got complex")
    layout = plan.layout
    departure = layout.departure(field)
    limit = DEPARTURE_TOLERANCE * jnp.maximum(jnp.max(jnp.abs(field)), 1e-30)
    return eqx.error_if(
        field,
        departure > limit,
        f"method = {method!r}: this raster is not the one its quadtree was decided on (a "
        f"shape moved more than the band of {layout.band} pixels, or changed where quads "
        "merged it); rebuild the model for it, raise the quad band, or use method = 'mft'",
    )


# --------------------------------------------------------------------------- polygons


def piece_radius(piece: Piece) -> float:
    """Largest distance (mm) of a piece's outline from its centroid (concrete)."""
    if piece.kind == "ellipse":
        return float(np.max(np.asarray(piece.semi_axes)))
    v = np.asarray(piece.vertices)
    return float(np.max(np.hypot(*(v - v.mean(axis=0)).T)))


def half_plane_freqs(output: AngularGrid, wavelength_nm) -> tuple[Array, Array]:
    """Rows ``f_y >= 0`` and columns ``-h .. h`` (cycles/mm) of the half plane computed."""
    h = output.npix // 2
    scale = output.pixel_scale_rad / (jnp.asarray(wavelength_nm) * 1e-6)
    return jnp.arange(h + 1) * scale, jnp.arange(-h, h + 1) * scale


def polygon_series_points(
    pieces: list[Piece], output: AngularGrid, longest_wavelength_nm: float
) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """The half-plane points that may need the small-frequency series (hashable).

    Found for the smallest piece at half its size and the longest wavelength (the points
    nearest 0 in frequency): a fit that shrinks a piece further still gets the series
    where the edge sum would lose digits worst.
    """
    radius = 0.5 * min(piece_radius(p) for p in pieces)
    fy, fx = half_plane_freqs(output, longest_wavelength_nm)
    rows, cols = series_points(np.asarray(fy), np.asarray(fx), max(radius, 1e-12))
    return tuple(int(r) for r in rows), tuple(int(c) for c in cols)


def overlap_residue(aperture: Aperture, grid: ApertureGrid) -> Float[Array, "n n"]:
    """``t - sum(open) + sum(block)``: what adding the shapes' transforms gets wrong."""
    t = aperture.transmission(grid)
    residue = t
    opens = [s for s in aperture.shapes if s.role == "open"]
    if not opens:
        residue = residue - 1.0
    for shape in aperture.shapes:
        sign = -1.0 if shape.role == "open" else 1.0
        residue = residue + sign * shape.coverage(grid)
    return residue


def overlap_plan(
    aperture: Aperture, grid: ApertureGrid, options: PolygonOptions
) -> QuadPlan | None:
    """Quads of the overlap residue, or None where the shapes do not overlap."""
    residue = np.asarray(overlap_residue(aperture, grid))
    if np.max(np.abs(residue)) <= DEPARTURE_TOLERANCE:
        return None
    layout = build_quadtree(residue, base_level=0, band=options.band)
    return make_plan(layout)


def pieces_transform(
    pieces: list[Piece], fy: Array, fx: Array, series_at: tuple[np.ndarray, np.ndarray]
) -> Complex[Array, "ny nx"]:
    """The sum of the pieces' exact transforms (mm^2) on the grid ``fy x fx``."""
    total = None
    for piece in pieces:
        if piece.kind == "ellipse":
            f = ellipse_transform(piece.centre, piece.semi_axes, piece.rotation_rad, fy, fx)
        else:
            f = polygon_transform(piece.vertices, fy, fx, series_at)
        total = piece.sign * f if total is None else total + piece.sign * f
    return total


def residue_half_plane(
    plan: QuadPlan, residue: Array, step: Array, npix: int
) -> Complex[Array, "h1 n1"]:
    """The residue's transform (px^2) on the half plane of :func:`half_plane_freqs`."""
    amps, _ = plan_amplitudes(plan, residue)
    t1, t2, t3, t4 = far_field_terms(plan, amps, step, npix)
    pos = (t1 - t4) - 1j * (t2 + t3)  # f_x >= 0
    neg = (t1 + t4) + 1j * (t2 - t3)  # f_x <= 0
    return jnp.concatenate([neg[:, :0:-1], pos], axis=1)


def aperture_pieces_checked(aperture, window_mm: float, arc_segments: int) -> list[Piece]:
    if not isinstance(aperture, Aperture):
        raise InputDataError(
            "method = 'polygon' transforms an Aperture of shapes; got "
            f"{type(aperture).__name__} (a raster needs method = 'quad', 'fft' or 'mft')"
        )
    return aperture_pieces(aperture, window_mm, arc_segments)
