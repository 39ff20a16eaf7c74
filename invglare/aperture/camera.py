"""Camera apertures: an n-blade diaphragm, cross-screen filters and dust on the lens.

A :class:`CameraAperture` is the camera counterpart of the eye aperture in the
obstacle-plane model of Kakimoto et al. (:mod:`invglare.models.kakimoto`): the
*pupil* ``P`` is the diaphragm (with any dust on the front element multiplied
in), and the *obstacle* ``t_o`` is the pattern of a filter screwed on in front
of the lens, which sits a distance ``d_o`` ahead of the diaphragm and therefore
slides over it as the light direction changes. The three methods the glare model
relies on are

- ``pupil_transmission(grid)``: amplitude transmission of the diaphragm (and dust);
- ``obstacle_transmission(grid, shift_mm)``: the filter pattern translated by
  ``shift_mm`` = (x, y) mm, i.e. ``t_o(x - shift)``;
- ``extent_mm()``: the diameter of the opening, for choosing a window.

Every continuous parameter is an array leaf (fit it through ``eqx.tree_at``);
counts and configuration (number of blades, number of line sets, noise octaves)
are static. Lengths are in mm, angles in degrees counter-clockwise from +x
towards +y, coordinates as in :class:`~invglare._core.grids.ApertureGrid`.

**Which diameter the f-number means.** ``focal_length_mm / f_number`` is taken
as the diameter of the *circle of equal area* (the equivalent entrance-pupil
diameter, which is what sets exposure). The polygon's circumscribed diameter is
then derived from it in closed form, including the circular segments added by
the blade rounding, so the conversion is exact and differentiable in the
rounding; with ``rounding = 1`` (a circular iris) the two diameters coincide.
"""

from __future__ import annotations

import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import ndtri
from jaxtyping import Array, ArrayLike, Float, UInt

from invglare._core.checks import as_float, check_positive, check_range
from invglare._core.grids import ApertureGrid
from invglare.aperture._checks import check_finite
from invglare.aperture._plain import plain
from invglare.aperture.shapes.coverage import strip_coverage
from invglare.aperture.shapes.primitives import (
    ImageMask,
    RegularPolygon,
    shifted_image_transmission,
)
from invglare.aperture.shapes.schema import shape_to_config
from invglare.errors import ConfigError, PhysicsRangeError

__all__ = [
    "CameraAperture",
    "CrossScreen",
    "Diaphragm",
    "Dust",
    "camera_to_config",
    "polygon_area_factor",
]


# --------------------------------------------------------------------------------------
# helpers


def _grid_dtype(grid: ApertureGrid):
    return jnp.asarray(grid.pitch_mm).dtype


# --------------------------------------------------------------------------------------
# diaphragm

# Below this half-angle (rad) the circular-segment area is taken from its series: the
# closed form subtracts two nearly equal numbers there (and is 0 / 0 at no rounding).
_SERIES_PHI = 0.2


def _segment_area_over_halfchord2(phi: Array) -> Array:
    """Area of a circular segment divided by (half chord)², as a function of its half-angle.

    With half chord ``w`` the radius is ``rho = w / sin(phi)`` and the area
    ``rho² (phi - sin(phi) cos(phi))``. Near ``phi = 0`` (a flat edge) that subtracts
    nearly equal numbers and ends in 0 / 0, so there it is evaluated from series:
    ``phi - sin(phi) cos(phi) = (2/3) phi³ (1 - u²/20 + u⁴/840 - u⁶/60480 + ...)`` with
    ``u = 2 phi``, and ``(phi / sin(phi))²``; the result ``~ (2/3) phi`` and its
    derivative are then accurate down to 0 (truncation error < 1e-9 relative).
    """
    small = phi < _SERIES_PHI
    # Double `where`: the unused branch must not see the 0 / 0 of the closed form.
    phi_big = jnp.where(small, _SERIES_PHI, phi)
    direct = (phi_big - jnp.sin(phi_big) * jnp.cos(phi_big)) / jnp.sin(phi_big) ** 2
    p2 = phi * phi
    u2 = 4.0 * p2
    numerator_over_phi3 = (2.0 / 3.0) * (1.0 - u2 / 20.0 + u2 * u2 / 840.0 - u2 * u2 * u2 / 60480.0)
    phi_over_sin = 1.0 + p2 * (
        1.0 / 6.0 + p2 * (7.0 / 360.0 + p2 * (31.0 / 15120.0 + p2 * 127.0 / 604800.0))
    )
    series = phi * numerator_over_phi3 * phi_over_sin**2
    return jnp.where(small, series, direct)


def polygon_area_factor(n_blades: int, rounding: ArrayLike) -> Float[Array, ""]:
    """Area of a (rounded) regular polygon of circumradius 1, i.e. area / R².

    The straight polygon has area ``(n/2) sin(2 pi / n)``; rounding bends each edge
    into an arc of sagitta ``rounding * (1 - cos(pi / n))`` (as
    :class:`~invglare.aperture.RegularPolygon` does), adding ``n`` circular segments.
    At ``rounding = 1`` the result is exactly ``pi`` (the circumscribed circle).

    **Example:**

    ```python
    polygon_area_factor(6, 0.0)   # 2.598..., the hexagon (3 sqrt(3) / 2)
    polygon_area_factor(6, 1.0)   # 3.14159...
    ```
    """
    n = int(n_blades)
    rounding = as_float(rounding)
    half = math.pi / n
    w = math.sin(half)  # half edge length at R = 1
    sagitta = rounding * (1.0 - math.cos(half))
    # The arc through the two corners with this sagitta subtends a half-angle of
    # 2 atan(s / w) at its centre.
    phi = 2.0 * jnp.arctan(sagitta / w)
    straight = 0.5 * n * math.sin(2.0 * half)
    return straight + n * w * w * _segment_area_over_halfchord2(phi)


class Diaphragm(eqx.Module):
    """An iris diaphragm of `n_blades` straight or curved blades.

    **Arguments:**

    - `n_blades`: number of blades (static integer >= 3).
    - `f_number`: the f-number N (> 0).
    - `focal_length_mm`: focal length of the lens (mm, > 0).
    - `rotation_deg`: rotation of the opening; at 0 one corner points along +x.
    - `rounding`: in ``[0, 1]``: 0 straight blades (a regular polygon), 1 a circle
      (see :class:`~invglare.aperture.RegularPolygon`).

    The opening has the area of a circle of diameter ``focal_length_mm / f_number``
    (:meth:`diameter_mm`, the equal-area convention); its corners lie on a circle
    of diameter :meth:`circumscribed_diameter_mm`, larger by
    ``sqrt(pi / polygon_area_factor(n, rounding))`` (1.0996 for a straight
    hexagon). The edge normals, which the diffraction streaks follow, point at
    ``rotation_deg + (2k + 1) * 180 / n_blades`` degrees.

    **Raises:** `PhysicsRangeError` for fewer than 3 blades, a non-positive f-number
    or focal length, or a rounding outside ``[0, 1]`` (concrete values).

    **Example:**

    ```python
    stop = Diaphragm(6, f_number=8.0, focal_length_mm=50.0, rounding=0.2)
    stop.diameter_mm()   # 6.25 mm (the equal-area diameter)
    ```
    """

    n_blades: int = eqx.field(static=True)
    f_number: Float[Array, ""] = eqx.field(converter=as_float)
    focal_length_mm: Float[Array, ""] = eqx.field(converter=as_float)
    rotation_deg: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)
    rounding: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)

    def __check_init__(self):
        n = self.n_blades
        if not isinstance(n, int | np.integer) or isinstance(n, bool):
            raise PhysicsRangeError(f"diaphragm n_blades must be an integer >= 3, got {n!r}")
        if n < 3:
            raise PhysicsRangeError(
                f"diaphragm n_blades must be >= 3 (a polygonal opening), got {n}; "
                "use rounding = 1 for a circular iris"
            )
        check_positive("diaphragm f_number", self.f_number)
        check_positive("diaphragm focal_length_mm", self.focal_length_mm, "mm")
        check_range("diaphragm rounding", self.rounding, 0.0, 1.0)
        check_finite("diaphragm rotation_deg", self.rotation_deg)

    def diameter_mm(self) -> Float[Array, ""]:
        """Equal-area (entrance pupil) diameter, ``focal_length_mm / f_number`` (mm)."""
        return self.focal_length_mm / self.f_number

    def circumscribed_diameter_mm(self) -> Float[Array, ""]:
        """Diameter (mm) of the circle through the corners, for the area of :meth:`diameter_mm`."""
        ratio = jnp.sqrt(math.pi / polygon_area_factor(self.n_blades, self.rounding))
        return self.diameter_mm() * ratio

    def area_mm2(self) -> Float[Array, ""]:
        """Area of the opening (mm²): ``pi / 4 * diameter_mm()²`` by construction."""
        return 0.25 * math.pi * self.diameter_mm() ** 2

    def polygon(self) -> RegularPolygon:
        """The opening as a :class:`~invglare.aperture.RegularPolygon` (role ``"open"``)."""
        return RegularPolygon(
            self.n_blades,
            self.circumscribed_diameter_mm(),
            rotation_deg=self.rotation_deg,
            rounding=self.rounding,
        )

    def coverage(self, grid: ApertureGrid) -> Float[Array, "n n"]:
        """Fraction of each pixel of `grid` inside the opening (anti-aliased)."""
        return self.polygon().coverage(grid)

    def extent_radius_mm(self) -> float:
        """Largest distance (mm) from the axis to the opening's edge (concrete values)."""
        return self.polygon().extent_radius_mm()

    def blade_normal_angles_deg(self) -> Float[Array, " n_blades"]:
        """Directions (deg) of the edges' outward normals, where the streaks point."""
        k = jnp.arange(self.n_blades)
        return self.rotation_deg + (2.0 * k + 1.0) * (180.0 / self.n_blades)


# --------------------------------------------------------------------------------------
# cross-screen filter


def _angles_array(x) -> Array:
    return jnp.atleast_1d(as_float(x))


class CrossScreen(eqx.Module):
    """A cross-screen ("star") filter: sets of parallel opaque lines at given angles.

    **Arguments:**

    - `angles_deg`: direction of the lines of each set (deg from +x); its length is
      the number of sets (a tuple or 1-D array; the count is fixed by the shape).
      ``(0, 90)`` is the cross of Kakimoto et al.'s fig. 5 d, ``(0, 60, 120)`` the
      trigonal filter of fig. 5 e. A set of lines at angle ``a`` diffracts light
      into a streak along ``a + 90`` deg.
    - `spacing_mm`: distance between neighbouring line centres (> 0).
    - `duty_cycle`: opaque fraction of each period, in ``(0, 1)``: the lines are
      ``duty_cycle * spacing_mm`` wide.
    - `line_offset_mm`: position of a line centre along the set's normal (so a
      line runs through ``line_offset_mm * normal``).

    Scalars apply to every set; arrays of one value per set are accepted too.

    **Rasterisation.** For each pixel the offset ``u`` from the nearest line centre
    (the projection on the normal, modulo the spacing) is computed, and the
    covered fraction of the line through that centre is the difference of two
    exact half-plane coverages (:func:`~invglare.aperture.edge_coverage`) at
    ``u -+ width / 2``, like the side of a capsule; the two neighbouring lines
    are added so that nothing jumps where the nearest line changes. Coverage is
    therefore anti-aliased and differentiable in spacing, duty cycle, offset,
    angle and shift. Lines closer than about 2 pixels cannot be represented by the
    raster (the pattern aliases); choose the window so that they are resolved.
    Where sets cross, the transmissions multiply (each set is an independent
    occluder, as in :func:`~invglare.aperture.occlude`).

    **Raises:** `PhysicsRangeError` for a spacing <= 0, a duty cycle outside
    ``(0, 1)``, non-finite angles or offsets, or no angle at all.

    **Example:**

    ```python
    star = CrossScreen((0.0, 60.0, 120.0), spacing_mm=0.05, duty_cycle=0.2)
    t = star.transmission(grid, shift_mm=(0.01, 0.0))
    ```
    """

    angles_deg: Float[Array, " sets"] = eqx.field(converter=_angles_array)
    spacing_mm: Float[Array, ""] = eqx.field(converter=as_float)
    duty_cycle: Float[Array, ""] = eqx.field(converter=as_float)
    line_offset_mm: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)

    def __check_init__(self):
        if self.angles_deg.ndim != 1 or self.angles_deg.shape[0] == 0:
            raise PhysicsRangeError(
                f"cross-screen angles_deg must be one or more angles, got shape "
                f"{self.angles_deg.shape}"
            )
        check_finite("cross-screen angles_deg", self.angles_deg)
        check_positive("cross-screen spacing_mm", self.spacing_mm, "mm")
        check_range(
            "cross-screen duty_cycle", self.duty_cycle, 0.0, 1.0, lo_open=True, hi_open=True
        )
        check_finite("cross-screen line_offset_mm", self.line_offset_mm)

    @property
    def n_sets(self) -> int:
        return self.angles_deg.shape[0]

    def line_width_mm(self) -> Float[Array, "*sets"]:
        """Width (mm) of each opaque line, ``duty_cycle * spacing_mm``."""
        return self.duty_cycle * self.spacing_mm

    def set_coverage(
        self, grid: ApertureGrid, shift_mm: Float[ArrayLike, " 2"] = (0.0, 0.0)
    ) -> Float[Array, "sets n n"]:
        """Per-set fraction of each pixel covered by the lines, shape ``(sets, n, n)``."""
        shift = as_float(shift_mm)
        y, x = grid.mesh_mm()
        x = x - shift[0]
        y = y - shift[1]
        a = jnp.deg2rad(self.angles_deg)[:, None, None]
        # The lines run along (cos a, sin a); their normal is (-sin a, cos a).
        nx, ny = -jnp.sin(a), jnp.cos(a)
        spacing = jnp.broadcast_to(self.spacing_mm, self.angles_deg.shape)[:, None, None]
        duty = jnp.broadcast_to(self.duty_cycle, self.angles_deg.shape)[:, None, None]
        offset = jnp.broadcast_to(self.line_offset_mm, self.angles_deg.shape)[:, None, None]
        u = nx * x + ny * y - offset
        # Offset from the nearest line centre; `round` has a zero derivative, so d/d(spacing)
        # is -m: the m-th line moves by m times the change of spacing, as it should.
        d = u - spacing * jnp.round(u / spacing)
        half = 0.5 * duty * spacing
        inv_px = 1.0 / grid.pitch_mm
        total = jnp.zeros(jnp.broadcast_shapes(d.shape, nx.shape), dtype=d.dtype)
        for j in (-1.0, 0.0, 1.0):
            dj = d - j * spacing
            total = total + strip_coverage((dj - half) * inv_px, (dj + half) * inv_px, nx, ny)
        return jnp.clip(total, 0.0, 1.0)

    def transmission(
        self, grid: ApertureGrid, shift_mm: Float[ArrayLike, " 2"] = (0.0, 0.0)
    ) -> Float[Array, "n n"]:
        """Amplitude transmission of the filter translated by `shift_mm` = (x, y) mm."""
        return jnp.prod(1.0 - self.set_coverage(grid, shift_mm), axis=0)


# --------------------------------------------------------------------------------------
# dust


def _hash_u32(x: Array) -> Array:
    """An integer hash of uint32 values (the "lowbias32" mixer): avalanche in a few ops."""
    x = x ^ (x >> 16)
    x = x * jnp.uint32(0x7FEB352D)
    x = x ^ (x >> 15)
    x = x * jnp.uint32(0x846CA68B)
    return x ^ (x >> 16)


def _as_u32(i: Array) -> Array:
    """Reinterpret int32 lattice indices (negative ones too) as uint32 bits."""
    return jax.lax.bitcast_convert_type(i.astype(jnp.int32), jnp.uint32)


def _quintic(t: Array) -> Array:
    """The C² fade ``6t⁵ - 15t⁴ + 10t³``: value noise without creases at lattice lines."""
    return t * t * t * (t * (t * 6.0 - 15.0) + 10.0)


def _fade_weight_moment() -> float:
    """Mean over a cell of ``f(t)² + (1 - f(t))²`` for the quintic fade (numerically)."""
    t = (np.arange(200000) + 0.5) / 200000
    f = t**3 * (t * (t * 6 - 15) + 10)
    return float(np.mean(f**2 + (1 - f) ** 2))


#: The variance of 2-D value noise with lattice values uniform in [-1, 1] (variance 1/3),
#: averaged over a cell: ``(1/3) * m**2``, m the 1-D moment of the fade weights.
_VALUE_NOISE_VAR = _fade_weight_moment() ** 2 / 3.0


def _key_to_data(key) -> Array:
    """uint32 key words from a typed or legacy PRNG key."""
    if hasattr(key, "dtype") and jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key):
        key = jax.random.key_data(key)
    arr = jnp.asarray(key)
    if arr.dtype != jnp.uint32 or arr.shape != (2,):
        raise ConfigError(
            f"dust key must be an integer seed or a jax.random key, got {arr.dtype} {arr.shape}"
        )
    return arr


class Dust(eqx.Module):
    """Dust and smudges on the front element: soft blotches from smooth value noise.

    **Arguments:**

    - `density`: roughly the fraction of the area covered by dust, in ``[0, 1]``.
    - `opacity`: how much light a blotch stops at its centre, in ``[0, 1]``.
    - `feature_size_mm`: lattice cell of the coarsest noise octave (> 0): blotches are
      about this size, with finer detail from the higher octaves.
    - `key`: an integer seed (recorded, so the layer can be written to a config) or
      a `jax.random` key. The pattern is a fixed function of the key.
    - `octaves`: number of noise octaves (static), each at half the cell size and half
      the amplitude of the previous one.
    - `edge_softness`: width of the smooth threshold in units of the noise's standard
      deviation (static): smaller gives crisper blotches and steeper gradients.
    - `seed`: only for `dataclasses.replace` (it records the integer `key`); leave it out.

    **Model.** The noise ``z`` (zero mean, unit variance on average) is a sum of
    octaves of value noise whose lattice values come from an integer hash of the
    key and the lattice indices, interpolated with a C² fade, so it is defined
    everywhere without a stored table. The dust coverage is
    ``opacity * sigmoid((z - z_density) / edge_softness)`` with
    ``z_density = Phi⁻¹(1 - density)``: if ``z`` were normal, the area beyond the
    threshold would be exactly `density`; for this noise it is close (value noise is
    slightly platykurtic). Coverage is smooth in density, opacity and feature size.

    **Example:**

    ```python
    dust = Dust(density=0.05, opacity=0.8, feature_size_mm=0.3, key=7)
    covered = dust.coverage(grid)   # (n, n) in [0, opacity]
    ```
    """

    density: Float[Array, ""]
    opacity: Float[Array, ""]
    feature_size_mm: Float[Array, ""]
    key: UInt[Array, " 2"]
    octaves: int = eqx.field(static=True)
    edge_softness: float = eqx.field(static=True)
    seed: int | None = eqx.field(static=True)

    def __init__(
        self,
        density: ArrayLike,
        opacity: ArrayLike,
        feature_size_mm: ArrayLike,
        key: int | ArrayLike = 0,
        octaves: int = 3,
        edge_softness: float = 0.25,
        seed: int | None = None,
    ):
        self.density = as_float(density)
        self.opacity = as_float(opacity)
        self.feature_size_mm = as_float(feature_size_mm)
        if isinstance(key, int | np.integer) and not isinstance(key, bool):
            self.seed = int(key)
            self.key = jax.random.key_data(jax.random.key(int(key)))
        else:
            # `seed` is only passed back in by `dataclasses.replace`, with the key it made.
            self.seed = seed
            self.key = _key_to_data(key)
        self.octaves = octaves
        self.edge_softness = edge_softness

    def __check_init__(self):
        check_range("dust density", self.density, 0.0, 1.0)
        check_range("dust opacity", self.opacity, 0.0, 1.0)
        check_positive("dust feature_size_mm", self.feature_size_mm, "mm")
        if not isinstance(self.octaves, int) or isinstance(self.octaves, bool) or self.octaves < 1:
            raise PhysicsRangeError(f"dust octaves must be an integer >= 1, got {self.octaves!r}")
        if not self.edge_softness > 0:
            raise PhysicsRangeError(f"dust edge_softness must be > 0, got {self.edge_softness!r}")

    def noise(self, grid: ApertureGrid) -> Float[Array, "n n"]:
        """The normalised noise field ``z`` on `grid` (zero mean, about unit variance)."""
        y, x = grid.mesh_mm()
        key = self.key.astype(jnp.uint32)
        total = jnp.zeros_like(x)
        norm2 = 0.0
        for octave in range(self.octaves):
            cell = self.feature_size_mm / (2.0**octave)
            amplitude = 0.5**octave
            salt = _hash_u32(key[0] ^ _hash_u32(key[1] + jnp.uint32(octave * 0x9E3779B9 % 2**32)))
            gx, gy = x / cell, y / cell
            ix, iy = jnp.floor(gx), jnp.floor(gy)
            fx, fy = _quintic(gx - ix), _quintic(gy - iy)
            ix, iy = ix.astype(jnp.int32), iy.astype(jnp.int32)

            def lattice(i, j, salt=salt):
                h = _hash_u32(_as_u32(i) ^ _hash_u32(_as_u32(j) ^ salt))
                # Top 24 bits: exactly representable in float32; uniform in [-1, 1).
                return (h >> 8).astype(x.dtype) * (2.0 / 2**24) - 1.0

            v00, v10 = lattice(ix, iy), lattice(ix + 1, iy)
            v01, v11 = lattice(ix, iy + 1), lattice(ix + 1, iy + 1)
            bottom = v00 + fx * (v10 - v00)
            top = v01 + fx * (v11 - v01)
            total = total + amplitude * (bottom + fy * (top - bottom))
            norm2 += amplitude**2
        return total / math.sqrt(norm2 * _VALUE_NOISE_VAR)

    def coverage(self, grid: ApertureGrid) -> Float[Array, "n n"]:
        """Fraction of light stopped by dust at each pixel, in ``[0, opacity]``."""
        # Keep the threshold finite at density 0 or 1 (there the gradient is simply 0).
        density = jnp.clip(self.density, 1e-6, 1.0 - 1e-6)
        threshold = ndtri(1.0 - density)
        z = self.noise(grid)
        return self.opacity * jax.nn.sigmoid((z - threshold) / self.edge_softness)


# --------------------------------------------------------------------------------------
# the camera


class CameraAperture(eqx.Module):
    """A camera's aperture: diaphragm, optional cross-screen filter and optional dust.

    **Arguments:**

    - `diaphragm`: the :class:`Diaphragm` (the pupil ``P`` of Kakimoto et al.).
    - `filter`: a :class:`CrossScreen` in front of the lens (the obstacle ``t_o``), or
      None.
    - `dust`: :class:`Dust` on the front element, or None. It sits at the lens, so it
      is part of the pupil and does not slide with the light direction.
    - `obstacle_image`: an :class:`~invglare.aperture.ImageMask` in the obstacle plane
      (any picture of a filter or an obstacle in front of the lens), or None; it
      multiplies the filter by ``1 - coverage`` (``role = "block"``: white passes) and
      slides with the light like it.
    - `pupil_image`: an :class:`~invglare.aperture.ImageMask` (``role = "open"``: white
      passes) multiplying the diaphragm's opening, or None: a diaphragm of any shape.

    Parameters are addressed by path, e.g.
    ``eqx.tree_at(lambda c: c.diaphragm.f_number, camera, 5.6)``.

    **Example:**

    ```python
    camera = CameraAperture(
        Diaphragm(6, f_number=8.0, focal_length_mm=50.0),
        filter=CrossScreen((0.0, 90.0), spacing_mm=0.2, duty_cycle=0.1),
    )
    grid = ApertureGrid.from_width(256, 1.05 * camera.extent_mm())
    field = camera.transmission(grid)
    ```
    """

    diaphragm: Diaphragm
    filter: CrossScreen | None = None
    dust: Dust | None = None
    obstacle_image: ImageMask | None = None
    pupil_image: ImageMask | None = None

    def __check_init__(self):
        if not isinstance(self.diaphragm, Diaphragm):
            raise ConfigError(
                f"camera diaphragm must be a Diaphragm, got {type(self.diaphragm).__name__}"
            )
        if self.filter is not None and not isinstance(self.filter, CrossScreen):
            raise ConfigError(
                f"camera filter must be a CrossScreen or None, got {type(self.filter).__name__}"
            )
        if self.dust is not None and not isinstance(self.dust, Dust):
            raise ConfigError(f"camera dust must be a Dust or None, got {type(self.dust).__name__}")
        for name in ("obstacle_image", "pupil_image"):
            value = getattr(self, name)
            if value is not None and not isinstance(value, ImageMask):
                raise ConfigError(
                    f"camera {name} must be an ImageMask or None, got {type(value).__name__}"
                )

    def pupil_transmission(self, grid: ApertureGrid) -> Float[Array, "n n"]:
        """Amplitude transmission of the diaphragm opening, dimmed by dust."""
        t = self.diaphragm.coverage(grid)
        if self.pupil_image is not None:
            t = t * self.pupil_image.coverage(grid)
        if self.dust is not None:
            t = t * (1.0 - self.dust.coverage(grid))
        return t

    def obstacle_transmission(
        self, grid: ApertureGrid, shift_mm: Float[ArrayLike, " 2"] = (0.0, 0.0)
    ) -> Float[Array, "n n"]:
        """The filter pattern (times the obstacle image) translated by `shift_mm` = (x, y) mm.

        All ones without a filter or image.
        """
        out = jnp.ones((grid.npix, grid.npix), dtype=_grid_dtype(grid))
        if self.obstacle_image is not None:
            out = out * shifted_image_transmission(self.obstacle_image, grid, shift_mm)
        if self.filter is None:
            return out
        return out * self.filter.transmission(grid, shift_mm)

    def transmission(self, grid: ApertureGrid) -> Float[Array, "n n"]:
        """The whole aperture, filter unshifted: ``t_o * P`` (the fixed mask of eq. 5)."""
        return self.obstacle_transmission(grid) * self.pupil_transmission(grid)

    def extent_mm(self) -> float:
        """Diameter (mm) of the disk about the axis holding the opening (concrete values)."""
        return 2.0 * self.diaphragm.extent_radius_mm()


# --------------------------------------------------------------------------------------
# configuration


def camera_to_config(camera: CameraAperture) -> dict[str, Any]:
    """The configuration table of a camera (the inverse of the reader `camera_from_config`).

    Values are plain Python numbers and lists, ready for TOML / JSON. A dust layer
    made from a `jax.random` key (not an integer seed) cannot be written and raises
    `ConfigError`.

    **Example:**

    ```python
    table = camera_to_config(camera)
    same = invglare.config.camera.camera_from_config(table)
    ```
    """
    d = camera.diaphragm
    table: dict[str, Any] = {
        "diaphragm": {
            "n_blades": int(d.n_blades),
            "f_number": plain(d.f_number),
            "focal_length_mm": plain(d.focal_length_mm),
            "rotation_deg": plain(d.rotation_deg),
            "rounding": plain(d.rounding),
        }
    }
    if camera.filter is not None:
        f = camera.filter
        for name in ("spacing_mm", "duty_cycle", "line_offset_mm"):
            if np.ndim(getattr(f, name)) != 0:
                raise ConfigError(
                    f"cannot write a cross-screen with one {name} per set as configuration; "
                    "the config takes one value for all sets"
                )
        table["cross_screen"] = {
            "angles_deg": [float(a) for a in np.asarray(f.angles_deg, dtype=float)],
            "spacing_mm": plain(f.spacing_mm),
            "duty_cycle": plain(f.duty_cycle),
            "line_offset_mm": plain(f.line_offset_mm),
        }
    if camera.dust is not None:
        dust = camera.dust
        if dust.seed is None:
            raise ConfigError(
                "a dust layer built from a jax.random key has no seed to write; "
                "build it with an integer key (seed)"
            )
        table["seed"] = int(dust.seed)
        table["dust"] = {
            "density": plain(dust.density),
            "opacity": plain(dust.opacity),
            "feature_size_mm": plain(dust.feature_size_mm),
            "octaves": int(dust.octaves),
            "edge_softness": float(dust.edge_softness),
        }
    for name in ("obstacle_image", "pupil_image"):
        image = getattr(camera, name)
        if image is not None:
            table[name] = {k: v for k, v in shape_to_config(image).items() if k != "kind"}
    return table
