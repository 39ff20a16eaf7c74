"""Closed-form diffraction patterns: references for the numerical propagators.

Every far-field PSF here is a **unit-energy intensity in sr⁻¹**: integrated over
the (paraxial, unbounded) plane of angles it gives 1. For a clear aperture of
area ``A`` illuminated by a plane wave, the peak is always ``A / lambda²``:
the far-field amplitude is the aperture's Fourier transform ``F(f)`` at spatial
frequency ``f = theta / lambda`` (cycles/mm, `theta` in rad), Parseval gives
``∫|F|² d²f = A``, and ``d²f = d²theta / lambda²``, so

    I(theta) = |F(theta / lambda)|² / (lambda² A),    I(0) = |F(0)|² / (lambda² A) = A / lambda².

This is the normalisation of :mod:`invglare.optics.fraunhofer` divided by the
pixel solid angle, so ``I(theta_k) * dtheta²`` is directly comparable with a
`fraunhofer_mft` pixel value. Angles are paraxial (``f = theta / lambda``, not
``sin theta / lambda``), as in the propagators.

Units: aperture sizes in mm, wavelengths in nm, angles in rad (the sampling
module's internal unit; convert degrees with `invglare._core.grids.deg_to_rad`).

All functions except :func:`fresnel_square_intensity` are pure `jax.numpy`
(differentiable, `jit`/`vmap`-able); they keep the input dtype and are accurate
to float64 round-off when `jax_enable_x64` is on.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Complex, Float

from invglare._core.checks import as_float
from invglare._core.grids import (
    AngularGrid,
    check_positive,
    check_wavelengths_nm,
    nm_to_mm,
)
from invglare._core.maths import safe_sqrt
from invglare.optics.bessel import bessel_j1, jinc

__all__ = [
    "airy_encircled_energy",
    "airy_pixel_psf",
    "airy_psf",
    "bessel_j1",
    "fresnel_square_intensity",
    "jinc",
    "polygon_area_mm2",
    "polygon_far_field",
    "polygon_fourier_transform",
    "rect_psf",
    "regular_polygon_vertices",
]


# ------------------------------------------------------------------------------ Airy


def _check_aperture(name: str, size_mm, wavelength_nm) -> None:
    check_positive(name, size_mm, "mm")
    check_wavelengths_nm(wavelength_nm)


def airy_psf(
    theta_rad: Float[ArrayLike, "*shape"],
    diameter_mm: Float[ArrayLike, ""],
    wavelength_nm: Float[ArrayLike, ""],
) -> Float[Array, "*shape"]:
    """Unit-energy Airy pattern of a clear circular pupil, in sr⁻¹.

        I(theta) = (pi D² / (4 lambda²)) [2 J1(v) / v]²,   v = pi D theta / lambda

    The peak ``pi D² / (4 lambda²) = A / lambda²`` (A the pupil area) follows from
    Parseval (see the module docstring); with ``∫_0^∞ J1(v)² / v dv = 1/2`` the
    integral over the plane is exactly 1.

    **Arguments:**

    - `theta_rad`: angle from the axis (rad, paraxial).
    - `diameter_mm`: pupil diameter (mm, > 0).
    - `wavelength_nm`: wavelength (nm).

    **Returns:** intensity in sr⁻¹, shape of `theta_rad` broadcast with the others.

    **Raises:** `PhysicsRangeError` (concrete inputs) for a non-positive diameter
    or a wavelength not in nm.

    **Example:**

    ```python
    airy_psf(0.0, 4.0, 550.0)   # pi * 4² / (4 * (5.5e-4)²) = 4.15e7 sr^-1
    ```
    """
    _check_aperture("diameter_mm", diameter_mm, wavelength_nm)
    lam = nm_to_mm(as_float(wavelength_nm))
    d = as_float(diameter_mm)
    v = math.pi * d * as_float(theta_rad) / lam
    return (math.pi * d * d / (4.0 * lam * lam)) * jinc(v) ** 2


def _pixel_offsets(oversample: int) -> np.ndarray:
    """Sub-sample offsets in units of a pixel: the midpoints of `oversample` equal cells."""
    return (np.arange(oversample) + 0.5) / oversample - 0.5


def airy_pixel_psf(
    grid: AngularGrid,
    diameter_mm: Float[ArrayLike, ""],
    wavelength_nm: Float[ArrayLike, ""],
    oversample: int = 1,
) -> Float[Array, "npix npix"]:
    """The Airy pattern as energy per pixel of an output grid.

    With ``oversample = 1`` (default) each pixel holds the sr⁻¹ value at its
    centre times the pixel solid angle ``dtheta²`` — the convention of
    `fraunhofer_mft`, which samples the far field at pixel centres. With
    ``oversample = s > 1`` it is the mean over ``s × s`` sub-pixel samples times
    ``dtheta²``: the energy a detector pixel integrates (midpoint rule). Either way
    the sum over an unbounded grid tends to 1.

    **Arguments:**

    - `grid`: the output grid (centre pixel ``npix // 2`` on the axis).
    - `diameter_mm`, `wavelength_nm`: as in :func:`airy_psf`.
    - `oversample`: sub-samples per pixel and axis (static, >= 1).

    **Returns:** ``(npix, npix)`` array, rows along y and columns along x.

    **Example:**

    ```python
    grid = AngularGrid(128, 0.002)
    psf = airy_pixel_psf(grid, 4.0, 550.0)   # sums to ~0.99 (the rest is outside)
    ```
    """
    if oversample < 1:
        raise ValueError(f"oversample must be >= 1, got {oversample}")
    _check_aperture("diameter_mm", diameter_mm, wavelength_nm)
    c = grid.coords_rad()
    acc = 0.0
    for oy in _pixel_offsets(oversample):
        for ox in _pixel_offsets(oversample):
            ty = c + oy * grid.pixel_scale_rad
            tx = c + ox * grid.pixel_scale_rad
            r2 = ty[:, None] ** 2 + tx[None, :] ** 2
            # sqrt(0) has an infinite derivative; the on-axis value does not need it.
            theta = safe_sqrt(r2)
            acc = acc + airy_psf(theta, diameter_mm, wavelength_nm)
    return acc * (grid.solid_angle_sr() / oversample**2)


def airy_encircled_energy(
    theta_rad: Float[ArrayLike, "*shape"],
    diameter_mm: Float[ArrayLike, ""],
    wavelength_nm: Float[ArrayLike, ""],
) -> Float[Array, "*shape"]:
    """Fraction of the Airy pattern's energy within `theta_rad`: ``1 - J0(v)² - J1(v)²``.

    Lord Rayleigh's result, with ``v = pi D theta / lambda``. J0 is obtained from
    J1 through ``J0(v) = J1(v) / v + J1'(v)`` (the derivative by autodiff).

    **Example:**

    ```python
    airy_encircled_energy(1.22 * 550e-6 / 4.0, 4.0, 550.0)   # 0.838, first dark ring
    ```
    """
    _check_aperture("diameter_mm", diameter_mm, wavelength_nm)
    lam = nm_to_mm(as_float(wavelength_nm))
    v = jnp.abs(math.pi * as_float(diameter_mm) * as_float(theta_rad) / lam)
    j1 = bessel_j1(v)
    # J1 acts elementwise, so a JVP with unit tangents is its derivative at every point.
    _, dj1 = jax.jvp(bessel_j1, (v,), (jnp.ones_like(v),))
    j0 = 0.5 * jinc(v) + dj1  # J1/v = jinc/2, finite at 0 (J0(0) = 1/2 + 1/2)
    return 1.0 - j0 * j0 - j1 * j1


# ------------------------------------------------------------------------------ rectangle


def rect_psf(
    theta_x_rad: Float[ArrayLike, "*shape"],
    theta_y_rad: Float[ArrayLike, "*shape"],
    width_mm: Float[ArrayLike, ""],
    height_mm: Float[ArrayLike, ""],
    wavelength_nm: Float[ArrayLike, ""],
) -> Float[Array, "*shape"]:
    """Unit-energy far field of a clear ``width × height`` rectangle, in sr⁻¹.

        I = (a b / lambda²) sinc²(a theta_x / lambda) sinc²(b theta_y / lambda)

    with ``sinc(u) = sin(pi u) / (pi u)``, ``a`` the width along x and ``b`` the
    height along y. Since ``∫ sinc²(a t / lambda) dt = lambda / a``, it integrates
    to 1.

    **Example:**

    ```python
    rect_psf(0.0, 0.0, 2.0, 1.0, 500.0)   # 2 / (5e-4)² = 8e6 sr^-1
    ```
    """
    _check_aperture("width_mm", width_mm, wavelength_nm)
    check_positive("height_mm", height_mm, "mm")
    lam = nm_to_mm(as_float(wavelength_nm))
    a = as_float(width_mm)
    b = as_float(height_mm)
    sx = jnp.sinc(a * as_float(theta_x_rad) / lam)
    sy = jnp.sinc(b * as_float(theta_y_rad) / lam)
    return (a * b / (lam * lam)) * (sx * sx) * (sy * sy)


# ------------------------------------------------------------------------------ Fresnel


def fresnel_square_intensity(
    x_mm: ArrayLike,
    y_mm: ArrayLike,
    side_mm: float,
    wavelength_nm: float,
    distance_mm: float,
) -> np.ndarray:
    """Fresnel diffraction of a square aperture: intensity relative to the incident wave.

    A square of side ``s`` centred on the axis, lit by a unit plane wave, observed
    at distance ``z`` in the Fresnel (paraxial) approximation. The field
    separates into x and y factors; along x, with ``w = sqrt(2 / (lambda z))``,

        u_x = [C(w (s/2 - x)) + C(w (s/2 + x))] + i [S(w (s/2 - x)) + S(w (s/2 + x))]

    where ``C``, ``S`` are the Fresnel integrals ``∫_0^u cos(pi t²/2) dt`` and
    ``∫_0^u sin(pi t²/2) dt``, and

        I / I0 = |u_x|² |u_y|² / 4.

    Deep inside the geometric shadow edge (``z -> 0``) this tends to 1 inside the
    square and 0 outside; for a Fresnel number ``s² / (lambda z) << 1`` it tends to
    the Fraunhofer pattern ``(s² / (lambda z))² sinc²(s x / (lambda z)) sinc²(s y /
    (lambda z))``.

    **numpy only** (uses `scipy.special.fresnel`, which JAX does not differentiate
    through with respect to the position); not `jit`-able.

    **Arguments:**

    - `x_mm`, `y_mm`: observation positions (mm), broadcast together.
    - `side_mm`: side of the square (mm).
    - `wavelength_nm`: wavelength (nm).
    - `distance_mm`: propagation distance (mm, > 0).

    **Returns:** float64 array of ``I / I0``.

    **Reference:** M. Born & E. Wolf, *Principles of Optics*, §8.7; J. W. Goodman,
    *Introduction to Fourier Optics*, §4.5.

    **Example:**

    ```python
    fresnel_square_intensity(0.0, 0.0, 1.0, 500.0, 100.0)   # on axis, Fresnel number 20
    ```
    """
    from scipy.special import fresnel

    check_positive("side_mm", side_mm, "mm")
    check_positive("distance_mm", distance_mm, "mm")
    check_wavelengths_nm(wavelength_nm)
    w = math.sqrt(2.0 / (float(wavelength_nm) * 1e-6 * float(distance_mm)))
    half = 0.5 * float(side_mm)

    def axis(u: np.ndarray) -> np.ndarray:
        s1, c1 = fresnel(w * (half - u))
        s2, c2 = fresnel(w * (half + u))
        return (c1 + c2) ** 2 + (s1 + s2) ** 2

    x = np.asarray(x_mm, dtype=np.float64)
    y = np.asarray(y_mm, dtype=np.float64)
    return 0.25 * axis(x) * axis(y)


# ------------------------------------------------------------------------------ polygons


def regular_polygon_vertices(
    n: int, diameter_mm: Float[ArrayLike, ""], rotation_deg: Float[ArrayLike, ""] = 0.0
) -> Float[Array, "n 2"]:
    """Counter-clockwise ``(x, y)`` vertices (mm) of a regular `n`-gon centred at 0.

    `diameter_mm` is the circumscribed diameter; at ``rotation_deg = 0`` a corner
    points along +x (the convention of `invglare.aperture.RegularPolygon`).
    """
    if n < 3:
        raise ValueError(f"a polygon needs n >= 3 vertices, got {n}")
    phi = jnp.deg2rad(as_float(rotation_deg)) + 2.0 * math.pi * jnp.arange(n) / n
    r = 0.5 * as_float(diameter_mm)
    return jnp.stack([r * jnp.cos(phi), r * jnp.sin(phi)], axis=-1)


def polygon_area_mm2(vertices_mm: Float[ArrayLike, "n 2"]) -> Float[Array, ""]:
    """Signed area (mm²) by the shoelace formula: positive for counter-clockwise vertices."""
    v = as_float(vertices_mm)
    w = jnp.roll(v, -1, axis=0)
    return 0.5 * jnp.sum(v[:, 0] * w[:, 1] - v[:, 1] * w[:, 0])


# Below |k| R = _TAYLOR_MAX (R = largest vertex distance from the origin) the edge sum loses
# digits to cancellation (relative error ~ eps / (|k| R)); there the Taylor series of the
# origin-fan triangles takes over, truncated after _TAYLOR_ORDER (error ~ (|k| R)^7 / 7!).
_TAYLOR_ORDER = 6
_TAYLOR_MAX = {np.dtype(np.float32): 0.5, np.dtype(np.float64): 0.05}


def _check_vertices(vertices_mm) -> None:
    if vertices_mm is None or not hasattr(vertices_mm, "shape"):
        vertices_mm = np.asarray(vertices_mm)
    if vertices_mm.ndim != 2 or vertices_mm.shape[-1] != 2 or vertices_mm.shape[0] < 3:
        raise ValueError(
            f"vertices_mm must have shape (n, 2) with n >= 3, got {tuple(vertices_mm.shape)}"
        )


def polygon_fourier_transform(
    fx_per_mm: Float[ArrayLike, "*shape"],
    fy_per_mm: Float[ArrayLike, "*shape"],
    vertices_mm: Float[ArrayLike, "n 2"],
) -> Complex[Array, "*shape"]:
    """Continuous Fourier transform of a uniform polygon, ``∫∫_P exp(-2 pi i f·r) dA`` (mm²).

    **Edge formula** (the divergence-theorem form used by Lee & Mittra 1983 and
    in computer graphics since): with ``k = 2 pi f``, edge vectors ``e`` (from one
    vertex to the next), edge midpoints ``m``, and ``sinc0(u) = sin(u) / u``,

        F(f) = (i / |k|²) sum_edges (k_x e_y - k_y e_x) exp(-i k·m) sinc0(k·e / 2)

    which follows from ``exp(-i k·r) = div(i k exp(-i k·r) / |k|²)``: the area
    integral becomes a sum of line integrals, each of a plane wave along one edge.
    Written with the midpoint and `sinc0`, the classical singular directions
    ``f ⟂ edge`` (``k·e = 0``) are not singular at all (`sinc0(0) = 1`, handled
    exactly by `jnp.sinc`, gradients included); only ``f = 0`` is, where the sum
    cancels to ``O(|k|²)``.

    **Near f = 0** (``|k| R`` below 0.05 in float64, 0.5 in float32, with ``R``
    the largest vertex distance from the origin) the polygon is split into the
    triangles ``(0, v_i, v_{i+1})`` and each is expanded as
    ``∫_T exp(l(r)) dA = (v_i × v_{i+1}) sum_n h_n(l_i, l_{i+1}) / (n + 2)!``, with
    ``h_n`` the complete homogeneous polynomial and ``l = -i k·v``; the series is
    cut after n = 6 (relative error < 1e-13 in float64, < 1e-7 in float32). The
    two branches agree to round-off at the switch. Give vertices about a nearby
    origin: a translation only multiplies ``F`` by a phase but enlarges ``R``.

    **Arguments:**

    - `fx_per_mm`, `fy_per_mm`: spatial frequencies (cycles/mm), broadcast.
    - `vertices_mm`: ``(n, 2)`` vertices ``(x, y)`` in mm of a simple polygon,
      either orientation (counter-clockwise gives ``F(0) = +area``).

    **Returns:** complex ``F`` in mm².

    **Reference:** S.-W. Lee, R. Mittra, "Fourier transform of a polygonal shape
    function and its application in electromagnetics", IEEE Trans. Antennas
    Propag. 31(1), 1983.
    """
    _check_vertices(vertices_mm)
    return _polygon_ft(as_float(fx_per_mm), as_float(fy_per_mm), as_float(vertices_mm))


@jax.jit
def _polygon_ft(fx: Array, fy: Array, v: Array) -> Array:
    dtype = jnp.result_type(fx, fy, v)
    v = v.astype(dtype)
    fx = fx.astype(dtype)
    fy = fy.astype(dtype)
    kx = 2.0 * math.pi * fx[..., None]
    ky = 2.0 * math.pi * fy[..., None]
    a = v
    b = jnp.roll(v, -1, axis=0)

    radius = jnp.sqrt(jnp.max(jnp.sum(v * v, axis=-1)))
    threshold = _TAYLOR_MAX.get(np.dtype(dtype), 0.05) / radius
    # Squared norms only: sqrt at k = 0 would put NaN into gradients.
    k_sq = kx[..., 0] ** 2 + ky[..., 0] ** 2
    near = k_sq < threshold**2

    # Edge sum, evaluated at a safe frequency where the Taylor branch is used.
    kx_e = jnp.where(near[..., None], threshold, kx)
    ky_e = jnp.where(near[..., None], 0.0, ky)
    e = b - a
    mid = 0.5 * (a + b)
    cross = kx_e * e[:, 1] - ky_e * e[:, 0]
    phase = kx_e * mid[:, 0] + ky_e * mid[:, 1]
    along = 0.5 * (kx_e * e[:, 0] + ky_e * e[:, 1])
    terms = cross * jnp.exp(-1j * phase) * jnp.sinc(along / math.pi)
    k2 = kx_e[..., 0] ** 2 + ky_e[..., 0] ** 2
    edge_sum = 1j * jnp.sum(terms, axis=-1) / k2

    # Taylor series of the origin fan, evaluated at a frequency inside its domain.
    scale = jnp.where(near, 1.0, threshold / jnp.sqrt(jnp.maximum(k_sq, threshold**2)))
    scale = scale[..., None]
    kx_t = kx * scale
    ky_t = ky * scale
    la = -1j * (kx_t * a[:, 0] + ky_t * a[:, 1])
    lb = -1j * (kx_t * b[:, 0] + ky_t * b[:, 1])
    twice_area = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    # h_n(la, lb) = la h_{n-1}(la, lb) + lb^n, accumulated order by order.
    h = jnp.ones_like(la)
    lb_pow = jnp.ones_like(lb)
    series = h / 2.0
    for n in range(1, _TAYLOR_ORDER + 1):
        lb_pow = lb_pow * lb
        h = la * h + lb_pow
        series = series + h / math.factorial(n + 2)
    taylor = jnp.sum(twice_area * series, axis=-1)

    return jnp.where(near, taylor, edge_sum)


def polygon_far_field(
    theta_x_rad: Float[ArrayLike, "*shape"],
    theta_y_rad: Float[ArrayLike, "*shape"],
    vertices_mm: Float[ArrayLike, "n 2"],
    wavelength_nm: Float[ArrayLike, ""],
) -> Float[Array, "*shape"]:
    """Unit-energy far field of a clear polygonal aperture, in sr⁻¹.

    ``I(theta) = |F(theta / lambda)|² / (lambda² A)`` with ``F`` from
    :func:`polygon_fourier_transform` and ``A`` the polygon's area; the peak is
    ``A / lambda²``. Exact (no sampling, no aliasing) at any angle.

    **Arguments:**

    - `theta_x_rad`, `theta_y_rad`: angles (rad), broadcast together.
    - `vertices_mm`: ``(n, 2)`` polygon vertices ``(x, y)`` in mm.
    - `wavelength_nm`: wavelength (nm).

    **Returns:** intensity in sr⁻¹.

    **Example:**

    ```python
    hexagon = regular_polygon_vertices(6, 4.0)
    polygon_far_field(0.0, 0.0, hexagon, 550.0)   # area / lambda²
    ```
    """
    check_wavelengths_nm(wavelength_nm)
    lam = nm_to_mm(as_float(wavelength_nm))
    tx = as_float(theta_x_rad)
    ty = as_float(theta_y_rad)
    f = polygon_fourier_transform(tx / lam, ty / lam, vertices_mm)
    area = jnp.abs(polygon_area_mm2(vertices_mm))
    return (jnp.real(f) ** 2 + jnp.imag(f) ** 2) / (lam * lam * area)
