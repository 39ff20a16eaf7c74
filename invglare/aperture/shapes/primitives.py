"""Soft aperture primitives: disks, ellipses, rounded polygons, capsules and image masks.

Each primitive is an equinox Module whose geometric parameters are array leaves
(so `jax.grad`, `jax.vmap` and `eqx.tree_at` reach them) and whose `role` is a
static string: ``"open"`` shapes transmit light (a pupil, a diaphragm),
``"block"`` shapes stop it (an eyelash, a wire, a grating line). How roles
combine is the business of :class:`invglare.aperture.Aperture`.

`coverage(grid)` returns, for every pixel of an
:class:`~invglare._core.grids.ApertureGrid`, the fraction of the pixel covered
by the shape, computed analytically from the shape's signed distance and outward
normal (see :func:`invglare.aperture.edge_coverage`), so that the result is
anti-aliased and differentiable in every parameter.

Coordinates follow :class:`~invglare._core.grids.ApertureGrid`: lengths in
mm, x along columns, y along rows, both 0 at index ``npix // 2``; centres are
given as ``(x, y)``. Angles are in degrees, counter-clockwise from +x towards +y.
"""

from __future__ import annotations

import abc
import math
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax.scipy.ndimage import map_coordinates
from jaxtyping import Array, ArrayLike, Float

from invglare._core.checks import as_float, check_positive, check_range, is_concrete
from invglare._core.colour import rec709_luminance_np
from invglare._core.grids import ApertureGrid
from invglare.aperture._checks import check_finite
from invglare.aperture.shapes.coverage import (
    capsule_edge_coverage,
    curved_edge_coverage,
)
from invglare.errors import ConfigError, InputDataError, PhysicsRangeError

#: The two roles a shape can play in an aperture.
ROLES = ("open", "block")


#: Radii (px) over which a disk's coverage passes from the area splat of a sub-pixel disk
#: to the edge model (see :class:`Disk`).
_SPLAT_START_PX, _SPLAT_END_PX = 0.35, 0.6

# --------------------------------------------------------------------------------------
# small helpers


def _safe_norm(dx: Array, dy: Array, fallback: tuple = (1.0, 0.0)) -> tuple[Array, Array, Array]:
    """Length of ``(dx, dy)`` and the unit vector along it, with finite gradients at 0.

    At the origin the direction is undefined; `fallback` is returned instead and the
    gradient is 0 (the double `where` keeps the unused branch from producing NaN).
    """
    r2 = dx * dx + dy * dy
    ok = r2 > 0.0
    r_safe = jnp.sqrt(jnp.where(ok, r2, 1.0))
    r = jnp.where(ok, r_safe, 0.0)
    # One division, not two (see the note in invglare.aperture.shapes.coverage).
    inv_r = 1.0 / r_safe
    ux = jnp.where(ok, dx * inv_r, fallback[0])
    uy = jnp.where(ok, dy * inv_r, fallback[1])
    return r, ux, uy


def _offsets(grid: ApertureGrid, center_mm: Array) -> tuple[Array, Array]:
    """Pixel-centre coordinates relative to a shape's centre, ``(dx, dy)`` in mm."""
    y, x = grid.mesh_mm()
    return x - center_mm[0], y - center_mm[1]


def _coverage_from_sdf(
    grid: ApertureGrid, sd_mm: Array, nx: Array, ny: Array, curvature_per_mm: Array
) -> Array:
    px = grid.pitch_mm
    return curved_edge_coverage(sd_mm * (1.0 / px), nx, ny, curvature_per_mm * px)


# --------------------------------------------------------------------------------------
# the shape interface


class AbstractShape(eqx.Module):
    """A soft 2-D shape in the aperture plane.

    Subclasses provide `coverage(grid)` (per-pixel covered fraction in ``[0, 1]``),
    `extent_radius_mm()` (distance from the grid origin to the farthest point of
    the shape, for choosing a window) and a static `role` (``"open"`` or ``"block"``).
    """

    # Every subclass declares `role: str = eqx.field(static=True, default=...)` as its last
    # field (declaring it here would put a defaulted field before their required ones).

    def __check_init__(self):
        if getattr(self, "role", None) not in ROLES:
            raise ConfigError(
                f"shape role must be one of {list(ROLES)}, got {getattr(self, 'role', None)!r}"
            )

    @abc.abstractmethod
    def coverage(self, grid: ApertureGrid) -> Float[Array, "n n"]:
        """Fraction of each pixel of `grid` covered by the shape, in ``[0, 1]``."""

    @abc.abstractmethod
    def extent_radius_mm(self) -> float:
        """Largest distance (mm) from the grid origin to a point of the shape (concrete)."""


class Disk(AbstractShape):
    """A disk of diameter `diameter_mm` centred at `center_mm` = (x, y) mm.

    Default role ``"open"`` (a pupil). Coverage includes the first-order curvature
    correction of :func:`invglare.aperture.curved_edge_coverage`: per-pixel errors are
    ~2.5e-4 at a radius of 64 px and ~5e-4 at 20 px.

    A disk well below a pixel (a cornea cell on a coarse raster) has no edge the
    half-plane model can follow: its coverage swung from 0 to 6 times its area with its
    place in the pixel. Below a radius of 0.6 px its area ``pi r^2`` is therefore
    splatted bilinearly onto the four nearest pixel centres (exactly its area, smooth in
    place and size), blended smoothly into the edge model between 0.35 and 0.6 px.
    """

    diameter_mm: Float[Array, ""] = eqx.field(converter=as_float)
    center_mm: Float[Array, " 2"] = eqx.field(converter=as_float, default=(0.0, 0.0))
    role: str = eqx.field(static=True, default="open")

    def __check_init__(self):
        check_positive("disk diameter_mm", self.diameter_mm, "mm")
        check_finite("disk center_mm", self.center_mm, (2,))

    def signed_distance_mm(self, grid: ApertureGrid) -> tuple[Array, Array, Array]:
        """Signed distance (mm, positive outside) and outward unit normal ``(nx, ny)``."""
        dx, dy = _offsets(grid, self.center_mm)
        r, nx, ny = _safe_norm(dx, dy)
        return r - 0.5 * self.diameter_mm, nx, ny

    def coverage(self, grid: ApertureGrid) -> Float[Array, "n n"]:
        edge = _coverage_from_sdf(grid, *self.signed_distance_mm(grid), 2.0 / self.diameter_mm)
        if is_concrete(self.diameter_mm) and is_concrete(grid.pitch_mm):
            if float(self.diameter_mm) >= 2.0 * _SPLAT_END_PX * float(grid.pitch_mm):
                return edge  # the usual case: no small-disk branch to compile
        radius_px = jnp.maximum(0.5 * self.diameter_mm / grid.pitch_mm, 0.0)
        dx, dy = _offsets(grid, self.center_mm)
        tent_x = jnp.maximum(1.0 - jnp.abs(dx / grid.pitch_mm), 0.0)
        tent_y = jnp.maximum(1.0 - jnp.abs(dy / grid.pitch_mm), 0.0)
        splat = math.pi * radius_px**2 * tent_x * tent_y
        t = jnp.clip((radius_px - _SPLAT_START_PX) / (_SPLAT_END_PX - _SPLAT_START_PX), 0.0, 1.0)
        w = t * t * (3.0 - 2.0 * t)
        return w * edge + (1.0 - w) * splat

    def extent_radius_mm(self) -> float:
        return float(np.hypot(*np.asarray(self.center_mm))) + 0.5 * float(self.diameter_mm)


class Ellipse(AbstractShape):
    """An ellipse with major axis `diameter_mm` and minor axis ``diameter_mm * (1 - ellipticity)``.

    The major axis points at `rotation_deg` from +x; `ellipticity` is in ``[0, 1)``
    (0 is a circle). The signed distance is the first-order estimate
    ``k0 (k0 - 1) / k1`` (``k0 = |p / s|``, ``k1 = |p / s**2|`` for semi-axes ``s``),
    exact on the boundary and accurate to second order in the distance, and the
    normal is the gradient direction of the implicit equation. The coverage is
    corrected for the local curvature (evaluated at the radial projection of the
    pixel centre onto the ellipse).
    Default role ``"open"`` (an astigmatic or tilted pupil).
    """

    diameter_mm: Float[Array, ""] = eqx.field(converter=as_float)
    ellipticity: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)
    rotation_deg: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)
    center_mm: Float[Array, " 2"] = eqx.field(converter=as_float, default=(0.0, 0.0))
    role: str = eqx.field(static=True, default="open")

    def __check_init__(self):
        check_positive("ellipse diameter_mm", self.diameter_mm, "mm")
        check_range("ellipse ellipticity", self.ellipticity, 0.0, 1.0, hi_open=True)
        check_finite("ellipse center_mm", self.center_mm, (2,))

    def _semi_axes(self) -> tuple[Array, Array]:
        a = 0.5 * self.diameter_mm
        return a, a * (1.0 - self.ellipticity)

    def _local_edge(self, grid: ApertureGrid) -> tuple[Array, Array, Array, Array]:
        """Signed distance (mm), outward normal and curvature (1/mm) of the nearby edge."""
        dx, dy = _offsets(grid, self.center_mm)
        th = jnp.deg2rad(self.rotation_deg)
        c, s = jnp.cos(th), jnp.sin(th)
        xl = c * dx + s * dy  # along the major axis
        yl = -s * dx + c * dy
        a, b = self._semi_axes()
        k0, _, _ = _safe_norm(xl / a, yl / b)
        # The gradient of k0**2 is along (x / a**2, y / b**2): its length is k1, its
        # direction the normal.
        k1, gx, gy = _safe_norm(xl / (a * a), yl / (b * b))
        inside_centre = k1 > 0.0
        k1_safe = jnp.where(inside_centre, k1, 1.0)
        sd = jnp.where(inside_centre, k0 * (k0 - 1.0) / k1_safe, -b)
        # Curvature at the boundary point p / k0 is 1 / (a**2 b**2 k1(p / k0)**3); k0 / k1 is
        # bounded, so this stays finite as p approaches the centre.
        ratio = k0 / k1_safe
        kappa = jnp.where(inside_centre, ratio**3 / (a * a * b * b), 0.0)
        return sd, c * gx - s * gy, s * gx + c * gy, kappa

    def signed_distance_mm(self, grid: ApertureGrid) -> tuple[Array, Array, Array]:
        """Approximate signed distance (mm, positive outside) and outward unit normal."""
        return self._local_edge(grid)[:3]

    def coverage(self, grid: ApertureGrid) -> Float[Array, "n n"]:
        return _coverage_from_sdf(grid, *self._local_edge(grid))

    def extent_radius_mm(self) -> float:
        a, b = (float(v) for v in self._semi_axes())
        th = math.radians(float(self.rotation_deg))
        t = np.linspace(0.0, 2.0 * math.pi, 4097)
        xl, yl = a * np.cos(t), b * np.sin(t)
        cx, cy = np.asarray(self.center_mm, dtype=float)
        x = cx + math.cos(th) * xl - math.sin(th) * yl
        y = cy + math.sin(th) * xl + math.cos(th) * yl
        # Sampling misses the farthest point by ~(pi / 4096)**2 / 2 relative; pad a little.
        return float(np.max(np.hypot(x, y))) * (1.0 + 1e-6)


class RegularPolygon(AbstractShape):
    """A regular `n_blades`-gon (camera diaphragm) with optionally rounded edges.

    **Arguments:**

    - `n_blades`: number of edges (static, >= 3).
    - `diameter_mm`: diameter of the circumscribed circle (the corners touch it).
    - `rotation_deg`: at 0 one corner points along +x.
    - `rounding`: in ``[0, 1]``; each straight edge is bent outwards into a circular
      arc through its two corners with sagitta ``rounding * (R - apothem)``, so
      0 is the straight polygon and 1 is exactly the circumscribed circle.
    - `center_mm`: (x, y) in mm.
    - `role`: default ``"open"``.

    The shape is the intersection of the `n_blades` edge regions (half-planes or
    disks). Each pixel's coverage is the minimum over edges of that edge's
    coverage (exact half-plane coverage, curvature-corrected for arcs): wherever
    one edge dominates this is the usual "largest signed distance, normal of the
    active edge" rule, and unlike that rule it stays continuous in the parameters
    where the active edge changes (near the corners). Pixels at a corner are
    over-covered by up to ~0.25 (the corner is treated as one straight edge).
    """

    n_blades: int = eqx.field(static=True)
    diameter_mm: Float[Array, ""] = eqx.field(converter=as_float)
    rotation_deg: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)
    rounding: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)
    center_mm: Float[Array, " 2"] = eqx.field(converter=as_float, default=(0.0, 0.0))
    role: str = eqx.field(static=True, default="open")

    def __check_init__(self):
        if not isinstance(self.n_blades, int | np.integer) or isinstance(self.n_blades, bool):
            raise PhysicsRangeError(
                f"polygon n_blades must be an integer >= 3, got {self.n_blades!r}"
            )
        if self.n_blades < 3:
            raise PhysicsRangeError(f"polygon n_blades must be >= 3, got {self.n_blades}")
        check_positive("polygon diameter_mm", self.diameter_mm, "mm")
        check_range("polygon rounding", self.rounding, 0.0, 1.0)
        check_finite("polygon center_mm", self.center_mm, (2,))

    def _edge_geometry(self) -> tuple[Array, Array, Array, Array]:
        """Edge normal angles (rad, shape (n,)), apothem, half edge length, sagitta (mm)."""
        n = self.n_blades
        radius = 0.5 * self.diameter_mm
        k = jnp.arange(n)
        phi = jnp.deg2rad(self.rotation_deg) + (2.0 * k + 1.0) * (math.pi / n)
        apothem = radius * math.cos(math.pi / n)
        half_edge = radius * math.sin(math.pi / n)
        sagitta = self.rounding * (radius - apothem)
        return phi, apothem, half_edge, sagitta

    def edge_distances_mm(self, grid: ApertureGrid) -> tuple[Array, Array, Array, Array]:
        """Per-edge signed distance (mm), outward normal and curvature (1/mm).

        Distances and normals have shape ``(n_blades, n, n)``; the curvature
        ``2 s / (w**2 + s**2)`` (0 for straight edges) is a scalar.

        Edge `k`'s region is a half-plane (rounding 0) or the disk bounded by the
        circle through its corners with sagitta `s`. The circle's distance
        ``|p - c| - rho`` (``rho = (w**2 + s**2) / (2 s)``) is multiplied through by
        ``2 s`` so that nothing divides by `s`; at ``s = 0`` it is exactly the
        half-plane distance ``u - apothem``.
        """
        dx, dy = _offsets(grid, self.center_mm)
        phi, apothem, half_edge, s = self._edge_geometry()
        cphi, sphi = jnp.cos(phi)[:, None, None], jnp.sin(phi)[:, None, None]
        u = cphi * dx + sphi * dy  # along the edge's outward normal
        v = -sphi * dx + cphi * dy  # along the edge
        d = u - (apothem + s)  # offset from the arc's apex, negative inside
        m = half_edge * half_edge + s * s  # = 2 s rho
        # (p - circle centre) * 2 s, in edge coordinates: (2 s d + m, 2 s v).
        gu = 2.0 * s * d + m
        gv = 2.0 * s * v
        q, nu, nv = _safe_norm(gu, gv)
        sd = (2.0 * s * (d * d + v * v) + 2.0 * d * m) / (q + m)
        nx = cphi * nu - sphi * nv
        ny = sphi * nu + cphi * nv
        return sd, nx, ny, 2.0 * s / m

    def signed_distance_mm(self, grid: ApertureGrid) -> tuple[Array, Array, Array]:
        """Signed distance (mm, largest over edges) and the active edge's outward normal."""
        sd, nx, ny, _ = self.edge_distances_mm(grid)
        k = jnp.argmax(sd, axis=0)[None]
        return tuple(jnp.take_along_axis(a, k, axis=0)[0] for a in (sd, nx, ny))

    def coverage(self, grid: ApertureGrid) -> Float[Array, "n n"]:
        sd, nx, ny, kappa = self.edge_distances_mm(grid)
        px = grid.pitch_mm
        return jnp.min(curved_edge_coverage(sd * (1.0 / px), nx, ny, kappa * px), axis=0)

    def extent_radius_mm(self) -> float:
        phi, apothem, half_edge, s = (np.asarray(v, dtype=float) for v in self._edge_geometry())
        v = np.linspace(-1.0, 1.0, 1025)[:, None] * half_edge
        m = half_edge**2 + s**2
        # Arc height above the chord at tangential offset v, in a form finite at s = 0.
        u = apothem + s - 2.0 * s * v**2 / (m + np.sqrt(np.maximum(m**2 - 4.0 * s**2 * v**2, 0)))
        cx, cy = np.asarray(self.center_mm, dtype=float)
        x = cx + np.cos(phi) * u - np.sin(phi) * v
        y = cy + np.sin(phi) * u + np.cos(phi) * v
        return float(np.max(np.hypot(x, y))) * (1.0 + 1e-6)


class Capsule(AbstractShape):
    """A line segment from `start_mm` to `end_mm` (each (x, y) mm) thickened to `thickness_mm`.

    The ends are round (radius ``thickness_mm / 2``). Default role ``"block"``: an
    eyelash, a wire, a grating line. Each pixel sees the capsule as a strip of the
    capsule's width across its local normal (the difference of two parallel
    half-planes), so lines thinner than a pixel keep the right area (0.3 % at a
    width of 0.6 px); the round ends get a curvature correction that stays
    continuous where they meet the sides. Per-pixel error vs the exact coverage:
    ~1.5e-3 at a width of 10 px, ~3e-3 at 3.4 px; end caps narrower than about a
    pixel are only roughly right, and so are segments shorter than about a pixel.
    """

    start_mm: Float[Array, " 2"] = eqx.field(converter=as_float)
    end_mm: Float[Array, " 2"] = eqx.field(converter=as_float)
    thickness_mm: Float[Array, ""] = eqx.field(converter=as_float)
    role: str = eqx.field(static=True, default="block")

    def __check_init__(self):
        check_finite("capsule start_mm", self.start_mm, (2,))
        check_finite("capsule end_mm", self.end_mm, (2,))
        check_positive("capsule thickness_mm", self.thickness_mm, "mm")

    def _axis_frame(self, grid: ApertureGrid):
        dx, dy = _offsets(grid, self.start_mm)
        ex, ey = self.end_mm[0] - self.start_mm[0], self.end_mm[1] - self.start_mm[1]
        length, ux, uy = _safe_norm(ex, ey)
        t = dx * ux + dy * uy  # along the axis from the start
        e = -dx * uy + dy * ux  # across the axis (left is positive)
        return dx, dy, length, ux, uy, t, e

    def _axis_distance(self, grid: ApertureGrid):
        """Distance (mm) from each pixel centre to the segment, the unit direction away from
        it, and the frame: (rho, nx, ny, at_end, sign of e, t, length, ux, uy)."""
        dx, dy, length, ux, uy, t, e = self._axis_frame(grid)
        sign = jnp.where(e >= 0.0, 1.0, -1.0)
        rho_mid, nx_mid, ny_mid = sign * e, -sign * uy, sign * ux
        rho_a, nx_a, ny_a = _safe_norm(dx, dy, fallback=(-ux, -uy))
        db_x, db_y = dx - length * ux, dy - length * uy
        rho_b, nx_b, ny_b = _safe_norm(db_x, db_y, fallback=(ux, uy))
        before, after = t < 0.0, t > length

        def pick(at_a, at_b, mid):
            return jnp.where(before, at_a, jnp.where(after, at_b, mid))

        rho = pick(rho_a, rho_b, rho_mid)
        nx, ny = pick(nx_a, nx_b, nx_mid), pick(ny_a, ny_b, ny_mid)
        return rho, nx, ny, before | after, sign, t, length, ux, uy

    def signed_distance_mm(self, grid: ApertureGrid) -> tuple[Array, Array, Array]:
        """Signed distance (mm, positive outside) and outward unit normal."""
        rho, nx, ny = self._axis_distance(grid)[:3]
        return rho - 0.5 * self.thickness_mm, nx, ny

    def coverage(self, grid: ApertureGrid) -> Float[Array, "n n"]:
        rho, nx, ny, at_end, sign, t, length, ux, uy = self._axis_distance(grid)
        # Lengths in px through one scalar reciprocal, not a division per pixel.
        inv_px = 1.0 / grid.pitch_mm
        half = 0.5 * self.thickness_mm
        # The round ends are corrected for their curvature (see `capsule_edge_coverage`).
        # The edge's curvature jumps from 0 to 1 / half where an end meets a straight side,
        # so the deviation of the edge from the local tangent line is modelled piecewise
        # (parabola on the arc, straight beyond its ends); both sides of the junction then
        # see the same edge and the coverage stays continuous. Tangent coordinates are in
        # px along (-ny, nx); an end's near junction lies at r sin(beta) from the vertex.
        r_px = half * inv_px
        t_near = r_px * sign * (nx * ux + ny * uy)
        return capsule_edge_coverage(
            (rho - half) * inv_px,
            (rho + half) * inv_px,
            nx,
            ny,
            r_px,
            t * inv_px,
            length * inv_px,
            t_near,
            sign,
            at_end,
        )

    def extent_radius_mm(self) -> float:
        a = float(np.hypot(*np.asarray(self.start_mm, dtype=float)))
        b = float(np.hypot(*np.asarray(self.end_mm, dtype=float)))
        return max(a, b) + 0.5 * float(self.thickness_mm)


# --------------------------------------------------------------------------------------
# image masks


def _validate_transmission(arr: np.ndarray, source: str) -> None:
    """Raise `InputDataError` unless `arr` is a finite 2-D array with values in [0, 1]."""
    if arr.ndim != 2:
        raise InputDataError(
            f"aperture image {source} must be a 2-D (grey or RGB) image, got shape {arr.shape}"
        )
    if arr.size == 0:
        raise InputDataError(f"aperture image {source} is empty (shape {arr.shape})")
    finite = np.isfinite(arr)
    if not np.all(finite):
        row, col = np.argwhere(~finite)[0]
        raise InputDataError(
            f"aperture image {source} holds non-finite values "
            f"({np.count_nonzero(~finite)} pixels, first {arr[row, col]} at row {row}, "
            f"column {col}); expected transmissions in [0, 1]"
        )
    lo, hi = float(arr.min()), float(arr.max())
    if lo < 0.0 or hi > 1.0:
        raise InputDataError(
            f"aperture image {source} has values in [{lo:g}, {hi:g}]; "
            "expected transmissions in [0, 1]"
        )


def _image_to_unit(raw: np.ndarray, source: str) -> np.ndarray:
    """Scale integer pixels to [0, 1] and turn RGB(A) into luminance (alpha is ignored)."""
    raw = np.asarray(raw)
    if raw.dtype == bool:
        img = raw.astype(np.float64)
    elif np.issubdtype(raw.dtype, np.unsignedinteger):
        img = raw.astype(np.float64) / np.iinfo(raw.dtype).max
    elif np.issubdtype(raw.dtype, np.floating):
        img = raw.astype(np.float64)
    else:
        raise InputDataError(
            f"aperture image {source} has pixel type {raw.dtype}; expected unsigned "
            "8/16-bit integers or floats in [0, 1]"
        )
    if img.ndim == 3 and img.shape[-1] in (3, 4):
        img = rec709_luminance_np(img[..., :3])
    elif img.ndim == 3 and img.shape[-1] in (1, 2):  # grey or grey + alpha
        img = img[..., 0]
    return img


class ImageMask(AbstractShape):
    """An aperture given as an image of transmissions in ``[0, 1]``.

    **Arguments:**

    - `transmission`: 2-D array ``(rows, cols)``. Orientation: **row 0 is the top of
      the image** (as in an image file), i.e. the largest y; column 0 is the
      smallest x. Image pixels are square.
    - `width_mm`: physical width of the whole image (all columns); its height is
      ``width_mm * rows / cols``.
    - `center_mm`: where the image centre lands, (x, y) in mm.
    - `rotation_deg`: counter-clockwise rotation of the image about its centre.
    - `role`: ``"open"`` (default): coverage is the transmission, 0 outside the
      image. ``"block"``: the image is an occluder; coverage is ``1 - transmission``
      and 0 outside the image (the occluder only exists where the image is).
    - `source`: where the image came from (a path, static); used in messages and
      by :func:`invglare.aperture.shape_to_config`.

    The image is resampled bilinearly at the pixel centres of the grid, which is
    differentiable in width, centre and rotation (piecewise linear). It is not
    area-averaged, so an image much finer than the grid aliases; prefer an image
    pitch close to the grid pitch.
    """

    transmission: Float[Array, "rows cols"] = eqx.field(converter=as_float)
    width_mm: Float[Array, ""] = eqx.field(converter=as_float)
    center_mm: Float[Array, " 2"] = eqx.field(converter=as_float, default=(0.0, 0.0))
    rotation_deg: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)
    role: str = eqx.field(static=True, default="open")
    source: str | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        if is_concrete(self.transmission):
            name = self.source if self.source is not None else "(array)"
            _validate_transmission(np.asarray(self.transmission), name)
        check_positive("image width_mm", self.width_mm, "mm")
        check_finite("image center_mm", self.center_mm, (2,))

    @classmethod
    def from_array(
        cls,
        array: ArrayLike,
        width_mm: float,
        center_mm: tuple[float, float] = (0.0, 0.0),
        rotation_deg: float = 0.0,
        role: str = "open",
        source: str | None = None,
    ) -> ImageMask:
        """Build a mask from an image array (grey or RGB(A); unsigned ints are scaled).

        Raises `InputDataError` for non-2-D data, non-finite values or values outside
        ``[0, 1]`` after scaling.
        """
        name = source if source is not None else "(array)"
        img = _image_to_unit(np.asarray(array), name)
        _validate_transmission(img, name)
        dtype = jnp.result_type(float)
        return cls(jnp.asarray(img, dtype=dtype), width_mm, center_mm, rotation_deg, role, source)

    @classmethod
    def from_file(
        cls,
        path: str | Path,
        width_mm: float,
        center_mm: tuple[float, float] = (0.0, 0.0),
        rotation_deg: float = 0.0,
        role: str = "open",
    ) -> ImageMask:
        """Read a PNG / JPEG / TIFF (or `.npy`) aperture image.

        Grey images are used as they are, RGB(A) is reduced to Rec. 709 luminance of
        the stored values (no sRGB decoding; alpha ignored); 8/16-bit integers are
        scaled to ``[0, 1]``. Raises `InputDataError` naming `path` if the file is
        missing or unreadable, not 2-D, non-finite, or outside ``[0, 1]``.
        """
        path = Path(path)
        if not path.is_file():
            raise InputDataError(f"aperture image {path} does not exist")
        try:
            if path.suffix.lower() == ".npy":
                raw = np.load(path, allow_pickle=False)
            else:
                import imageio.v3 as iio  # only image masks need it

                raw = iio.imread(path)
        except Exception as err:
            raise InputDataError(f"cannot read aperture image {path}: {err}") from err
        return cls.from_array(raw, width_mm, center_mm, rotation_deg, role, source=str(path))

    def _sample(self, grid: ApertureGrid, outside: float) -> Array:
        rows, cols = self.transmission.shape
        dx, dy = _offsets(grid, self.center_mm)
        th = jnp.deg2rad(self.rotation_deg)
        c, s = jnp.cos(th), jnp.sin(th)
        xl = c * dx + s * dy  # image frame (undo the rotation)
        yl = -s * dx + c * dy
        pix = self.width_mm / cols
        col = xl / pix + 0.5 * (cols - 1)
        row = 0.5 * (rows - 1) - yl / pix  # row 0 is the top, the largest y
        img = self.transmission.astype(col.dtype)
        return map_coordinates(img, [row, col], order=1, mode="constant", cval=outside)

    def coverage(self, grid: ApertureGrid) -> Float[Array, "n n"]:
        if self.role == "open":
            return self._sample(grid, 0.0)
        return 1.0 - self._sample(grid, 1.0)

    def extent_radius_mm(self) -> float:
        rows, cols = self.transmission.shape
        w = float(self.width_mm)
        h = w * rows / cols
        th = math.radians(float(self.rotation_deg))
        cx, cy = np.asarray(self.center_mm, dtype=float)
        corners = np.array([[sx * w / 2, sy * h / 2] for sx in (-1, 1) for sy in (-1, 1)])
        x = cx + math.cos(th) * corners[:, 0] - math.sin(th) * corners[:, 1]
        y = cy + math.sin(th) * corners[:, 0] + math.cos(th) * corners[:, 1]
        return float(np.max(np.hypot(x, y)))


def shifted_image_transmission(
    image: ImageMask, grid: ApertureGrid, shift_mm: Float[ArrayLike, " 2"]
) -> Float[Array, "n n"]:
    """An obstacle image's transmission ``1 - coverage``, translated by `shift_mm` = (x, y).

    Clear (1) outside the image; differentiable in the shift and the image's placement.
    """
    moved = eqx.tree_at(lambda m: m.center_mm, image, image.center_mm + jnp.asarray(shift_mm))
    return 1.0 - moved.coverage(grid)
