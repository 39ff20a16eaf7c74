"""Tests of invglare.aperture.shapes: pixel coverage, soft primitives, composition, configs
(written by `shape_to_config`, read by `invglare.config.shapes.shape_from_config`).

Tolerances are stated in the test names / docstrings; the measured errors they guard are
noted beside them (float32 unless a test says float64).
"""

from __future__ import annotations

import math

import equinox as eqx
import helpers
import imageio.v3 as iio
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from invglare._core.grids import ApertureGrid
from invglare.aperture import (
    SHAPE_KINDS,
    Aperture,
    Capsule,
    Disk,
    Ellipse,
    ImageMask,
    RegularPolygon,
    curved_edge_coverage,
    edge_coverage,
    occlude,
    shape_to_config,
    strip_coverage,
    union,
)
from invglare.aperture.shapes.coverage import sliver_integral
from invglare.config.shapes import shape_from_config
from invglare.errors import ConfigError, InputDataError, PhysicsRangeError

# ---------------------------------------------------------------------------------------
# ground truths


def _clipped_square_area(sd: float, nx: float, ny: float) -> float:
    """Exact area of the unit pixel (centred at 0) where ``n . q + sd <= 0``, by polygon
    clipping (Sutherland-Hodgman against one half-plane) and the shoelace formula."""
    square = [(-0.5, -0.5), (0.5, -0.5), (0.5, 0.5), (-0.5, 0.5)]
    level = [nx * x + ny * y + sd for x, y in square]
    kept = []
    for i in range(4):
        (px, py), (qx, qy) = square[i], square[(i + 1) % 4]
        fp, fq = level[i], level[(i + 1) % 4]
        if fp <= 0:
            kept.append((px, py))
        if (fp < 0) != (fq < 0) and fp != fq:
            t = fp / (fp - fq)
            kept.append((px + t * (qx - px), py + t * (qy - py)))
    if len(kept) < 3:
        return 0.0
    x = np.array([k[0] for k in kept])
    y = np.array([k[1] for k in kept])
    return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _disk_truth(npix: int, radius_px: float, cx: float, cy: float, sub: int = 512) -> np.ndarray:
    """Per-pixel disk coverage (pitch 1): `sub` sub-columns per pixel, each column's covered
    height computed exactly. Error < 1e-5 except at the disk's far left/right (~1e-4)."""
    c = (np.arange(npix) - npix // 2).astype(float)
    x = c[None, :, None] - 0.5 + (np.arange(sub) + 0.5) / sub
    y = c[:, None, None]
    half = np.sqrt(np.maximum(radius_px**2 - (x - cx) ** 2, 0.0))
    covered = np.minimum(y + 0.5, cy + half) - np.maximum(y - 0.5, cy - half)
    return np.clip(covered, 0.0, None).mean(axis=-1)


def _random_normals(rng, n):
    theta = rng.uniform(0.0, 2.0 * math.pi, n)
    return np.cos(theta), np.sin(theta)


# ---------------------------------------------------------------------------------------
# edge_coverage


def test_edge_coverage_axis_aligned_is_clipped_ramp_1e6():
    sd = np.linspace(-1.2, 1.2, 49, dtype=np.float32)
    expected = np.clip(0.5 - sd, 0.0, 1.0)
    for nx, ny in [(1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0)]:
        got = np.asarray(edge_coverage(sd, nx, ny))
        np.testing.assert_allclose(got, expected, atol=1e-6)  # measured 0 (exact)


def test_edge_coverage_exact_vs_polygon_clipping_2e7_float32_1e12_float64():
    rng = np.random.default_rng(1)
    sd = rng.uniform(-1.0, 1.0, 1000)
    nx, ny = _random_normals(rng, 1000)
    exact = np.array([_clipped_square_area(*a) for a in zip(sd, nx, ny, strict=True)])
    got32 = np.asarray(edge_coverage(*(v.astype(np.float32) for v in (sd, nx, ny))))
    assert got32.dtype == np.float32
    assert np.abs(got32 - exact).max() < 2e-7  # measured 1.0e-7
    with helpers.x64():
        got64 = np.asarray(edge_coverage(jnp.asarray(sd), jnp.asarray(nx), jnp.asarray(ny)))
    assert got64.dtype == np.float64
    assert np.abs(got64 - exact).max() < 1e-12  # measured 2e-16


def test_strip_coverage_is_a_difference_of_edges_against_polygon_clipping_1e12():
    """A strip between two parallel edges: exact area of the pixel between them (float64)."""
    rng = np.random.default_rng(4)
    sd = rng.uniform(-1.0, 1.0, 300)
    width = rng.uniform(0.0, 1.5, 300)
    nx, ny = _random_normals(rng, 300)
    exact = np.array(
        [
            _clipped_square_area(s, x, y) - _clipped_square_area(s + w, x, y)
            for s, w, x, y in zip(sd, width, nx, ny, strict=True)
        ]
    )
    with helpers.x64():
        got = np.asarray(strip_coverage(*(jnp.asarray(v) for v in (sd, sd + width, nx, ny))))
    assert np.abs(got - exact).max() < 1e-12


def test_edge_coverage_vs_brute_force_supersampling_1e3():
    """1000 x 1000 sub-samples per pixel (sampling error <= 5e-4); 40 random (sd, angle)."""
    rng = np.random.default_rng(2)
    sub = (np.arange(1000) + 0.5) / 1000 - 0.5
    sd = rng.uniform(-1.0, 1.0, 40)
    nx, ny = _random_normals(rng, 40)
    got = np.asarray(edge_coverage(sd, nx, ny))
    for i in range(40):
        offset = nx[i] * sub[:, None] + ny[i] * sub[None, :]
        brute = np.mean(offset <= -sd[i])
        assert abs(got[i] - brute) < 1e-3, (sd[i], nx[i], ny[i])  # measured 1.2e-5


def test_edge_coverage_limits_and_finite_gradients_on_axes():
    # Outside beyond (|nx| + |ny|) / 2 the coverage is exactly 0, inside exactly 1.
    n = np.array([0.6, 0.8])
    assert float(edge_coverage(0.7001, *n)) == 0.0
    assert float(edge_coverage(-0.7001, *n)) == 1.0
    # On the axes b = 0: gradients stay finite and d/d sd is minus the density (1 in the
    # middle of an axis-aligned ramp).
    grad = jax.grad(edge_coverage, argnums=(0, 1, 2))
    for sd in [-0.6, -0.49, -0.2, 0.0, 0.3, 0.49, 0.6]:
        g = np.array([float(v) for v in grad(jnp.float32(sd), 1.0, 0.0)])
        assert np.all(np.isfinite(g)), (sd, g)
        expected = -1.0 if abs(sd) < 0.5 else 0.0
        assert g[0] == pytest.approx(expected), sd


def test_edge_coverage_gradient_matches_fd_float64():
    """Autodiff against central differences at steps 1e-5 and 5e-6 (rtol 1e-5)."""
    with helpers.x64():
        rng = np.random.default_rng(3)
        for _ in range(10):
            sd0 = rng.uniform(-0.9, 0.9)
            theta0 = rng.uniform(0.0, 2.0 * math.pi)
            helpers.assert_grad_converges(
                lambda s, t=theta0: edge_coverage(s, jnp.cos(t), jnp.sin(t)), sd0, eps=1e-5
            )
            helpers.assert_grad_converges(
                lambda t, s=sd0: edge_coverage(s, jnp.cos(t), jnp.sin(t)), theta0, eps=1e-5
            )


def test_curved_edge_coverage_reduces_to_flat_at_zero_curvature():
    rng = np.random.default_rng(4)
    sd = rng.uniform(-1.0, 1.0, 200).astype(np.float32)
    nx, ny = (v.astype(np.float32) for v in _random_normals(rng, 200))
    np.testing.assert_array_equal(
        np.asarray(curved_edge_coverage(sd, nx, ny, 0.0)), np.asarray(edge_coverage(sd, nx, ny))
    )


def test_curved_edge_coverage_written_derivatives_match_fd_float64_1e7():
    """The hand-written JVP against central differences (step 1e-6) in each of sd, nx, ny
    and the curvature, at random points of every regime (flat tails, ramps, chord clipped
    or free, convex and concave); points within 1e-4 of a kink are skipped (the function
    is piecewise, its one-sided slopes differ there). Absolute error < 1e-7, measured
    ~1e-10. Reverse mode and a tangent that is zero in the normal agree with it."""
    rng = np.random.default_rng(11)
    n = 4000
    with helpers.x64():
        sd = jnp.asarray(rng.uniform(-1.2, 1.2, n))
        nx, ny = (jnp.asarray(v) for v in _random_normals(rng, n))
        kappa = jnp.asarray(rng.uniform(-0.4, 0.4, n))
        args = [sd, nx, ny, kappa]
        eps = 1e-6
        checked = 0
        for i in range(4):
            unit = [jnp.zeros(n)] * 4
            unit[i] = jnp.ones(n)
            _, jvp = jax.jvp(curved_edge_coverage, tuple(args), tuple(unit))

            def at(step, i=i):
                moved = list(args)
                moved[i] = moved[i] + step
                return np.asarray(curved_edge_coverage(*moved))

            fd = (at(eps) - at(-eps)) / (2 * eps)
            one_sided = (at(1e-4) - at(0.0)) / 1e-4, (at(0.0) - at(-1e-4)) / 1e-4
            smooth = np.abs(one_sided[0] - one_sided[1]) < 1e-3
            assert np.max(np.abs(np.asarray(jvp) - fd)[smooth]) < 1e-7, i
            checked += int(smooth.sum())
        assert checked > 3 * n  # most points are away from kinks
        weights = jnp.asarray(rng.standard_normal(n))
        rev = jax.grad(lambda s: jnp.sum(curved_edge_coverage(s, nx, ny, kappa) * weights))(sd)
        fwd = jax.jvp(lambda s: curved_edge_coverage(s, nx, ny, kappa), (sd,), (jnp.ones(n),))[1]
        np.testing.assert_allclose(np.asarray(rev), np.asarray(fwd * weights), atol=1e-12)


# ---------------------------------------------------------------------------------------
# areas against closed forms (pitch 0.05 mm, 160 x 160 pixels)

GRID = ApertureGrid(160, 0.05)
PX = 0.05


def _area_px(shape, grid=GRID) -> float:
    return float(np.sum(np.asarray(shape.coverage(grid), dtype=np.float64)))


@pytest.mark.parametrize("radius_px", [64.0, 20.37])
def test_disk_area_1e5(radius_px):
    disk = Disk(2 * radius_px * PX, center_mm=(0.013, -0.021))
    rel = _area_px(disk) / (math.pi * radius_px**2) - 1
    assert abs(rel) < 1e-5  # measured 8e-9 (r = 64), 3.6e-7 (r = 20); 2e-5 without curvature


def test_a_sub_pixel_disk_carries_its_area_wherever_it_lies():
    """Issue 27 (2): a cornea cell a fifth of a pixel across blocks its own area. The edge
    model gave 0 to 6 times it with the cell's place in the pixel (the eye of
    examples/eye_daylight.toml: 6 % on average); the area splat gives it exactly, and the
    blend into the edge model stays within 15 % between 0.35 and 0.6 px."""
    grid = ApertureGrid(16, 1.0)
    rng = np.random.default_rng(3)
    for radius_px in (0.1, 0.2, 0.3, 0.45, 0.55):
        for centre in rng.uniform(-0.5, 0.5, (6, 2)):
            area = _area_px(Disk(2 * radius_px, centre), grid)
            tol = 1e-5 if radius_px <= 0.35 else 0.15
            assert area == pytest.approx(math.pi * radius_px**2, rel=tol), (radius_px, centre)
    # smooth in the size across the blend
    d = jax.grad(lambda r: jnp.sum(Disk(2 * r, (0.2, 0.1)).coverage(grid)))(0.45)
    assert np.isfinite(float(d)) and float(d) > 0


@pytest.mark.parametrize("n", [5, 6, 8])
def test_polygon_area_1e4(n):
    radius_px = 64.0
    poly = RegularPolygon(n, 2 * radius_px * PX, rotation_deg=7.3, center_mm=(0.01, 0.02))
    exact = n / 2 * radius_px**2 * math.sin(2 * math.pi / n)
    assert abs(_area_px(poly) / exact - 1) < 1e-4  # measured 6.9e-6 .. 2.7e-5 (corners)


@pytest.mark.parametrize("n", [5, 6, 8])
def test_fully_rounded_polygon_is_the_circumscribed_disk_1e5(n):
    radius_px = 64.0
    poly = RegularPolygon(n, 2 * radius_px * PX, rotation_deg=11.0, rounding=1.0)
    assert abs(_area_px(poly) / (math.pi * radius_px**2) - 1) < 1e-5  # measured <= 1.6e-6
    # Per pixel the same as the disk up to float32 rounding (measured 7.6e-5: the arc's
    # distance is assembled from mm-sized terms, and 1 ulp of 3 mm is 5e-6 px here).
    disk = Disk(2 * radius_px * PX)
    np.testing.assert_allclose(poly.coverage(GRID), disk.coverage(GRID), atol=3e-4)


def test_half_rounded_polygon_area_between_polygon_and_disk_1e4():
    """Area of a rounded hexagon = polygon + n circular segments of sagitta s."""
    n, radius_px, rounding = 6, 60.0, 0.5
    apothem = radius_px * math.cos(math.pi / n)
    half = radius_px * math.sin(math.pi / n)
    s = rounding * (radius_px - apothem)
    rho = (half**2 + s**2) / (2 * s)
    segment = rho**2 * math.asin(half / rho) - half * (rho - s)
    exact = n / 2 * radius_px**2 * math.sin(2 * math.pi / n) + n * segment
    poly = RegularPolygon(n, 2 * radius_px * PX, rotation_deg=3.0, rounding=rounding)
    assert abs(_area_px(poly) / exact - 1) < 1e-4  # measured 9.4e-6


def test_ellipse_area_1e4():
    a, e = 60.0, 0.4
    ell = Ellipse(2 * a * PX, ellipticity=e, rotation_deg=23.0, center_mm=(0.1, -0.2))
    assert abs(_area_px(ell) / (math.pi * a * a * (1 - e)) - 1) < 1e-4  # measured 4.7e-6


@pytest.mark.parametrize(("radius_px", "tol"), [(10.3, 1e-4), (0.3, 5e-3)])
def test_capsule_area(radius_px, tol):
    """Thick capsule within 1e-4 (measured 1.3e-7); sub-pixel line within 5e-3 (2.6e-3)."""
    start, end = np.array([-2.0, -1.1]), np.array([1.7, 2.3])
    length_px = float(np.linalg.norm(end - start)) / PX
    cap = Capsule(tuple(start), tuple(end), 2 * radius_px * PX)
    exact = 2 * radius_px * length_px + math.pi * radius_px**2
    assert abs(_area_px(cap) / exact - 1) < tol


@pytest.mark.parametrize(
    ("radius_px", "cx", "cy"), [(64.0, 0.0, 0.0), (64.0, 0.31, -0.27), (20.3, 0.1, 0.2)]
)
def test_disk_per_pixel_vs_supersampled_truth_1e3(radius_px, cx, cy):
    """Per pixel within 1e-3 (measured 2.5e-4 at r = 64, 5.3e-4 at r = 20.3)."""
    grid = ApertureGrid(160, 1.0)
    got = np.asarray(Disk(2 * radius_px, (cx, cy)).coverage(grid))
    truth = _disk_truth(160, radius_px, cx, cy)
    assert np.abs(got - truth).max() < 1e-3
    assert got.min() >= 0.0 and got.max() <= 1.0


def test_disk_orientation_rows_are_y_columns_are_x():
    grid = ApertureGrid(32, 1.0)
    cov = np.asarray(Disk(5.0, center_mm=(6.0, -4.0)).coverage(grid), dtype=np.float64)
    rows, cols = np.indices(cov.shape) - 16
    centroid = (np.sum(rows * cov) / cov.sum(), np.sum(cols * cov) / cov.sum())
    np.testing.assert_allclose(centroid, (-4.0, 6.0), atol=1e-5)


def _capsule_truth(npix, x0, x1, cy, r, sub=512):
    """Per-pixel coverage (pitch 1) of a horizontal capsule from (x0, cy) to (x1, cy): sub-
    columns per pixel, each column's covered height exact."""
    c = (np.arange(npix) - npix // 2).astype(float)
    x = c[None, :, None] - 0.5 + (np.arange(sub) + 0.5) / sub
    y = c[:, None, None]
    beyond = np.where(x < x0, x0 - x, np.where(x > x1, x - x1, 0.0))
    half = np.sqrt(np.maximum(r * r - beyond**2, 0.0))
    covered = np.minimum(y + 0.5, cy + half) - np.maximum(y - 0.5, cy - half)
    return np.clip(covered, 0.0, None).mean(axis=-1)


@pytest.mark.parametrize(("radius_px", "tol"), [(5.3, 3e-3), (1.7, 5e-3)])
def test_capsule_per_pixel_vs_supersampled_truth(radius_px, tol):
    """Measured 1.5e-3 (r = 5.3 px) and 2.7e-3 (r = 1.7 px), mostly where an end cap
    meets a side."""
    grid = ApertureGrid(64, 1.0)
    x0, x1, cy = -15.3, 12.6, 0.37
    got = np.asarray(Capsule((x0, cy), (x1, cy), 2 * radius_px).coverage(grid))
    assert np.abs(got - _capsule_truth(64, x0, x1, cy, radius_px)).max() < tol


def test_sliver_integral_vs_quadrature_1e7():
    rng = np.random.default_rng(7)
    for _ in range(20):
        t0 = rng.uniform(-1.0, 1.0)
        t1, t2 = t0 - rng.uniform(0.0, 1.0), t0 + rng.uniform(0.0, 1.0)
        lo, hi = np.sort(rng.uniform(-1.5, 1.5, 2))
        t = np.linspace(lo, hi, 20001)
        profile = 0.5 * ((t - t0) ** 2 - np.maximum(t1 - t, 0) ** 2 - np.maximum(t - t2, 0) ** 2)
        with helpers.x64():
            got = float(sliver_integral(lo, hi, t0, t1, t2))
        assert got == pytest.approx(np.trapezoid(profile, t), abs=1e-7)


@pytest.mark.parametrize(
    ("make", "slope"),
    [
        # a capsule end slides past pixel centres: end / side switches must not jump
        (lambda x: Capsule((x, 0.123), (9.0, 0.123), 4.4), 2.5),
        # (an end narrower than a pixel has a steep, but continuous, coverage: ~4 / px)
        (lambda x: Capsule((x, 0.123), (9.0, 0.123), 0.37), 5.0),
        # a polygon turns: the active edge switches near every corner
        (lambda x: RegularPolygon(5, 20.0, x, 0.0), 1.5),
        (lambda x: RegularPolygon(6, 20.0, x, 0.6), 1.5),
    ],
)
def test_coverage_is_continuous_in_parameters(make, slope):
    """Between parameter values 2e-3 apart (px or deg) no pixel's coverage changes by
    more than `slope` * 2e-3: a jump (e.g. a curvature correction switched on at an end)
    fails. Measured: 3.7e-3, 7.7e-3, 2.5e-4, 7.6e-5."""
    grid = ApertureGrid(32, 1.0)
    coverage = jax.jit(jax.vmap(lambda x: make(x).coverage(grid)))
    with helpers.x64():
        steps = jnp.linspace(-3.0, 3.0, 3001)
        cov = np.asarray(coverage(steps))
    assert np.abs(np.diff(cov, axis=0)).max() < slope * 2e-3


def test_polygon_corner_points_along_plus_x():
    grid = ApertureGrid(64, 1.0)
    cov = np.asarray(RegularPolygon(3, 40.0).coverage(grid))
    # Along +x the triangle reaches its corner at 20 px, along -x only the apothem (10 px).
    assert cov[32, 32 + 18] == 1.0 and cov[32, 32 + 22] == 0.0
    assert cov[32, 32 - 9] == 1.0 and cov[32, 32 - 11] == 0.0


def test_signed_distances_are_consistent_with_coverage():
    grid = ApertureGrid(64, 0.1)
    shapes = [
        Disk(3.3),
        Ellipse(4.1, 0.3, 20.0),
        RegularPolygon(6, 4.0, 10.0, 0.4),
        Capsule((-2.0, -1.0), (1.5, 2.0), 0.9),
    ]
    for shape in shapes:
        sd, nx, ny = (np.asarray(v) for v in shape.signed_distance_mm(grid))
        cov = np.asarray(shape.coverage(grid))
        assert np.all(cov[sd < -0.1] == 1.0) and np.all(cov[sd > 0.1] == 0.0), shape
        np.testing.assert_allclose(np.hypot(nx, ny), 1.0, atol=1e-5)


# ---------------------------------------------------------------------------------------
# gradients: float64 autodiff vs central differences


def _check_gradients(make_shape, names, p0, step=1e-5, npix=64, pitch=0.05, seed=0):
    """Float64 autodiff vs central differences for every entry of a parameter vector.

    The scalar is ``f(p) = sum(coverage(make_shape(p)) * W)`` with fixed random weights
    `W`; it is jitted once (and its gradient once) so that each parameter costs only four
    evaluations: central differences at ``step * max(|p_i|, 0.1)`` and half that, the
    finer within rtol 1e-5 (+ the rounding floor) and the discrepancy at least halved by the
    halving (`helpers.assert_fd_converges`).
    """
    with helpers.x64():
        weights = jnp.asarray(np.random.default_rng(seed).uniform(0.5, 1.5, (npix, npix)))
        grid = ApertureGrid(npix, jnp.float64(pitch))
        f = jax.jit(lambda p: jnp.sum(make_shape(p).coverage(grid) * weights))
        p0 = jnp.asarray(p0, dtype=jnp.float64)
        ad = np.asarray(jax.jit(jax.grad(f))(p0))
        for i, name in enumerate(names):
            x0 = float(p0[i])
            try:
                helpers.assert_fd_converges(
                    lambda x, i=i: f(p0.at[i].set(x)),
                    x0,
                    float(ad[i]),
                    step * max(abs(x0), 0.1),
                    rtol=1e-5,
                )
            except AssertionError as err:
                raise AssertionError(f"{name}: {err}") from err
            assert abs(ad[i]) > 1e-3, name  # the parameter really moves the coverage


# Parameter values avoid pixel-aligned points (where the coverage has kinks).
GRADIENT_CASES = {
    "disk": (
        lambda p: Disk(p[0], p[1:3]),
        ["diameter_mm", "center x", "center y"],
        [2.3456, 0.0123, -0.0371],
    ),
    "ellipse": (
        lambda p: Ellipse(p[0], p[1], p[2], p[3:5]),
        ["diameter_mm", "ellipticity", "rotation_deg", "center x", "center y"],
        [2.5432, 0.31, 17.3, 0.011, 0.023],
    ),
    "polygon": (
        lambda p: RegularPolygon(6, p[0], p[1], p[2], p[3:5]),
        ["diameter_mm", "rotation_deg", "rounding", "center x", "center y"],
        [2.4321, 8.7, 0.37, 0.0113, -0.0217],
    ),
    "polygon rounding ~0": (
        lambda p: RegularPolygon(5, p[0], p[1], p[2]),
        ["diameter_mm", "rotation_deg", "rounding"],
        [2.4321, 8.7, 1e-4],
    ),
    "capsule": (
        lambda p: Capsule(p[0:2], p[2:4], p[4]),
        ["start x", "start y", "end x", "end y", "thickness_mm"],
        [-1.2137, -1.0271, 1.17, 0.91, 0.31],
    ),
    "sub-pixel capsule": (
        lambda p: Capsule(p[0:2], p[2:4], p[4]),
        ["start x", "start y", "end x", "end y", "thickness_mm"],
        [-1.2137, -1.0271, 1.17, 0.91, 0.0213],
    ),
    "capsule shorter than thick": (
        lambda p: Capsule(p[0:2], p[2:4], p[4]),
        ["start x", "start y", "end x", "end y", "thickness_mm"],
        [0.1137, -0.0271, 0.217, 0.031, 0.41],
    ),
}


@pytest.mark.parametrize("case", list(GRADIENT_CASES))
def test_shape_gradients_match_finite_differences_float64_rtol_1e5(case):
    """Measured agreement: relative 1e-8 or better for every parameter."""
    _check_gradients(*GRADIENT_CASES[case])


def test_capsule_written_derivatives_match_fd_per_pixel_float64_1e7():
    """Capsule coverage's hand-written JVP (`capsule_edge_coverage`) pixel by pixel against
    central differences (step 1e-7 mm) in each of start, end, thickness and the grid
    pitch, over random capsules from sub-pixel to 8 px thick, long and shorter than thick;
    pixels within 1e-5 mm of a kink are skipped (one-sided slopes differ by > 1e-3).
    Absolute error < 1e-7 per pixel, measured ~1e-9; reverse mode agrees to 1e-12."""
    rng = np.random.default_rng(12)

    @jax.jit
    def f(p):
        return Capsule(p[0:2], p[2:4], p[4]).coverage(ApertureGrid(48, p[5]))

    jvp = jax.jit(lambda p, d: jax.jvp(f, (p,), (d,))[1])
    grad = jax.jit(jax.grad(lambda p, w: jnp.sum(f(p) * w)))
    columns = jax.jit(jax.jacfwd(lambda p, w: jnp.sum(f(p) * w)))
    with helpers.x64():
        checked = 0
        for i in range(12):
            start = rng.uniform(-0.8, 0.8, 2)
            end = start + rng.uniform(-0.05, 0.05, 2) if i < 3 else rng.uniform(-0.8, 0.8, 2)
            p0 = jnp.asarray(np.r_[start, end, rng.uniform(0.02, 0.4), 0.05])
            for k in range(6):
                step = jnp.asarray(np.eye(6)[k])

                def at(h, step=step):
                    return np.asarray(f(p0 + h * step))

                fd = (at(1e-7) - at(-1e-7)) / 2e-7
                kinked = np.abs((at(1e-5) - at(0.0)) - (at(0.0) - at(-1e-5))) / 1e-5 > 1e-3
                err = np.abs(np.asarray(jvp(p0, step)) - fd)[~kinked]
                assert np.max(err) < 1e-7, (i, k)
                checked += int((~kinked & (np.abs(fd) > 0)).sum())
            weights = jnp.asarray(rng.standard_normal((48, 48)))
            np.testing.assert_allclose(
                np.asarray(grad(p0, weights)), np.asarray(columns(p0, weights)), atol=1e-12
            )
        assert checked > 1000  # edge pixels with a nonzero derivative (1669)


@pytest.mark.parametrize("role", ["open", "block"])
def test_image_mask_gradients_match_finite_differences_float64_rtol_1e5(role):
    """Bilinear resampling is piecewise linear in the coordinates, with kinks wherever a
    grid point crosses an image pixel centre; with ~2000 samples a 1e-6 step crosses one
    now and then, so the steps here are 5e-8 and 2.5e-8 of the parameter's scale (float64
    keeps the difference accurate). Between kinks the function is linear, so both
    differences are exact up to rounding: the check is their agreement, not a rate."""
    image = np.random.default_rng(5).uniform(0.0, 1.0, (24, 20))
    _check_gradients(
        lambda p: ImageMask(image, p[0], p[1:3], p[3], role),
        ["width_mm", "center x", "center y", "rotation_deg"],
        [2.21, 0.037, -0.052, 13.7],
        step=5e-8,
    )


def _all_kinds():
    return [
        Disk(1.0),
        Ellipse(1.0, 0.2),
        RegularPolygon(5, 1.0, rounding=0.5),
        Capsule((0, 0), (1, 1), 0.1),
        ImageMask(np.ones((3, 3)), 1.0),
    ]


def test_dtypes_float32_by_default_float64_under_x64():
    for shape in _all_kinds():
        out = jax.eval_shape(shape.coverage, ApertureGrid(16, 0.1))
        assert out.dtype == jnp.float32 and out.shape == (16, 16)
    with helpers.x64():
        grid = ApertureGrid(16, jnp.float64(0.1))
        for shape in _all_kinds():
            assert jax.eval_shape(shape.coverage, grid).dtype == jnp.float64


# ---------------------------------------------------------------------------------------
# transformations


def _test_aperture():
    return Aperture(
        [
            RegularPolygon(7, 3.1, 4.0, 0.2),
            Disk(2.9, (0.1, 0.05)),
            Capsule((-1.5, -1.2), (1.4, 1.0), 0.12),
            Ellipse(0.7, 0.3, 40.0, (0.6, -0.4), role="block"),
        ]
    )


@pytest.mark.slow
def test_jit_equals_eager():
    """float32: atol 5e-5 (XLA fuses and reorders; 1 ulp of a 1.5 mm coordinate moves the
    coverage by ~3e-6 at this pitch; measured 1.1e-5). float64: atol 1e-12."""
    transmission = eqx.filter_jit(lambda ap, g: ap.transmission(g))
    grid = ApertureGrid(96, 0.04)
    aperture = _test_aperture()
    eager = aperture.transmission(grid)
    np.testing.assert_allclose(transmission(aperture, grid), eager, atol=5e-5)
    with helpers.x64():
        grid = ApertureGrid(96, jnp.float64(0.04))
        aperture = _test_aperture()
        eager = aperture.transmission(grid)
        assert eager.dtype == jnp.float64
        np.testing.assert_allclose(transmission(aperture, grid), eager, atol=1e-12)


def test_vmap_over_diameters_equals_loop():
    grid = ApertureGrid(48, 0.05)
    diameters = jnp.array([0.8, 1.33, 1.9, 2.25])

    @jax.jit
    def cov(d):
        return Aperture([RegularPolygon(6, d, 5.0, 0.3), Disk(d * 0.9)]).transmission(grid)

    batched = jax.vmap(cov)(diameters)
    looped = jnp.stack([cov(d) for d in diameters])
    # float32, batched vs unbatched kernels: atol 5e-5 as for jit (measured 1.7e-6)
    np.testing.assert_allclose(np.asarray(batched), np.asarray(looped), atol=5e-5)


def test_grad_through_aperture_by_path_is_finite_and_nonzero():
    grid = ApertureGrid(64, 0.05)
    aperture = _test_aperture()

    def loss(d):
        ap = eqx.tree_at(lambda a: a.shapes[0].diameter_mm, aperture, d)
        return jnp.sum(ap.transmission(grid) ** 2)

    g = jax.jit(jax.grad(loss))(jnp.float32(3.1))
    assert np.isfinite(float(g)) and float(g) > 0.0


def test_validation_is_skipped_for_tracers():
    grid = ApertureGrid(8, 0.1)
    # A negative diameter under jit cannot be checked; it must not raise or produce NaN.
    out = jax.jit(lambda d: Disk(d).coverage(grid))(-1.0)
    assert np.all(np.asarray(out) == 0.0)


# ---------------------------------------------------------------------------------------
# composition


def test_union_and_occlude():
    a, b = jnp.array([0.0, 0.5, 1.0]), jnp.array([0.5, 0.5, 0.2])
    np.testing.assert_allclose(union(a, b), [0.5, 0.75, 1.0])
    np.testing.assert_allclose(occlude(jnp.ones(3), a, b), [0.5, 0.25, 0.0])
    assert float(union()) == 0.0


def test_aperture_transmission_roles():
    grid = ApertureGrid(64, 0.05)
    disk = Disk(2.5)
    wire = Capsule((-2.0, 0.1), (2.0, -0.1), 0.2)
    # Open shapes are united and block shapes multiply.
    t = Aperture([disk, wire]).transmission(grid)
    np.testing.assert_allclose(t, disk.coverage(grid) * (1 - wire.coverage(grid)), atol=1e-7)
    # Without an open shape the whole window is open.
    grating = Aperture([wire, Capsule((0.0, -2.0), (0.0, 2.0), 0.1)]).transmission(grid)
    assert float(grating.max()) == 1.0 and float(grating[0, 0]) == 1.0
    assert float(grating[32, 32]) == 0.0
    # Two overlapping open disks: a union, never above 1.
    both = Aperture([Disk(2.0, (-0.3, 0.0)), Disk(2.0, (0.3, 0.0))]).transmission(grid)
    assert float(both.max()) <= 1.0 and float(both[32, 32]) == 1.0


def test_aperture_extent():
    aperture = Aperture(
        [Disk(2.0, (0.3, 0.4)), RegularPolygon(6, 3.0), Capsule((0.0, 0.0), (9.0, 0.0), 1.0)]
    )
    assert aperture.extent_mm() == pytest.approx(3.0, rel=1e-5)  # the capsule blocks
    assert Aperture([Disk(2.0, (0.3, 0.4))]).extent_mm() == pytest.approx(3.0)
    # An off-centre ellipse: the farthest point is at the end of the major axis.
    assert Aperture([Ellipse(2.0, 0.5, 90.0, (0.0, 1.0))]).extent_mm() == pytest.approx(
        4.0, rel=1e-5
    )
    # A grating alone: the extent of its lines.
    assert Aperture([Capsule((-1.0, 0.0), (1.0, 0.0), 0.2)]).extent_mm() == pytest.approx(2.2)
    with pytest.raises(ConfigError, match="no shapes"):
        Aperture([]).extent_mm()
    with pytest.raises(ConfigError, match="shapes\\[1\\]"):
        Aperture([Disk(1.0), "disk"])


# ---------------------------------------------------------------------------------------
# validation


@pytest.mark.parametrize(
    ("build", "error", "match"),
    [
        (lambda: Disk(-1.5), PhysicsRangeError, "diameter_mm.*-1.5"),
        (lambda: Disk(0.0), PhysicsRangeError, "diameter_mm.*0"),
        (lambda: Disk(1.0, (0.0, float("nan"))), PhysicsRangeError, "center_mm"),
        (lambda: Disk(1.0, role="opaque"), ConfigError, "opaque"),
        (lambda: Ellipse(2.0, ellipticity=1.0), PhysicsRangeError, "ellipticity.*1"),
        (lambda: Ellipse(2.0, ellipticity=-0.2), PhysicsRangeError, "ellipticity.*-0.2"),
        (lambda: Ellipse(-2.0), PhysicsRangeError, "diameter_mm.*-2"),
        (lambda: RegularPolygon(2, 3.0), PhysicsRangeError, "n_blades.*2"),
        (lambda: RegularPolygon(6.0, 3.0), PhysicsRangeError, "n_blades.*6.0"),
        (lambda: RegularPolygon(6, 3.0, rounding=1.5), PhysicsRangeError, "rounding.*1.5"),
        (lambda: RegularPolygon(6, 3.0, rounding=-0.1), PhysicsRangeError, "rounding.*-0.1"),
        (lambda: RegularPolygon(6, -3.0), PhysicsRangeError, "diameter_mm.*-3"),
        (lambda: Capsule((0, 0), (1, 1), -0.25), PhysicsRangeError, "thickness_mm.*-0.25"),
        (lambda: Capsule((0, 0, 0), (1, 1), 0.25), PhysicsRangeError, "start_mm"),
        (lambda: ImageMask(np.ones((4, 4)), 0.0), PhysicsRangeError, "width_mm.*0"),
        (lambda: ImageMask(np.full((4, 4), 1.25), 1.0), InputDataError, "1.25"),
        (lambda: ImageMask(np.ones(4), 1.0), InputDataError, "2-D"),
    ],
)
def test_bad_values_raise(build, error, match):
    with pytest.raises(error, match=match):
        build()


# ---------------------------------------------------------------------------------------
# image masks


def test_image_mask_orientation_row0_is_top():
    image = np.zeros((8, 8))
    image[:4, :] = 1.0  # top half of the picture transmits
    image[:, :2] = 0.0  # ... except its two left-most columns
    grid = ApertureGrid(8, 1.0)
    # Pixel centres of the grid sit half a pixel off the image's pixel centres, so shift
    # the mask by half a pixel to sample the image pixels exactly.
    cov = np.asarray(ImageMask(image, 8.0, center_mm=(-0.5, -0.5)).coverage(grid))
    # Rows with y > 0 (row index > 4 in the grid) are the top of the image.
    np.testing.assert_array_equal(cov, np.flipud(image))


def test_image_mask_rotation_by_90_degrees():
    rng = np.random.default_rng(6)
    image = rng.uniform(0.0, 1.0, (9, 9))
    grid = ApertureGrid(9, 1.0)
    turned = np.asarray(ImageMask(image, 9.0, rotation_deg=90.0).coverage(grid))
    # Counter-clockwise by 90 deg in (x, y up) is np.rot90 of the picture (row 0 at top);
    # on the grid (row 0 at the bottom) that is the flipped version.
    np.testing.assert_allclose(turned, np.flipud(np.rot90(image)), atol=1e-5)


def test_image_mask_outside_and_block_role():
    grid = ApertureGrid(16, 1.0)
    open_mask = ImageMask(np.full((4, 4), 0.25), 4.0)
    cov = np.asarray(open_mask.coverage(grid))
    assert cov[0, 0] == 0.0 and cov[8, 8] == pytest.approx(0.25)
    block = ImageMask(np.full((4, 4), 0.25), 4.0, role="block")
    t = np.asarray(Aperture([block]).transmission(grid))
    assert t[0, 0] == 1.0 and t[8, 8] == pytest.approx(0.25)


def test_image_mask_of_a_disk_resembles_the_disk():
    grid = ApertureGrid(64, 0.05)
    disk = Disk(2.0)
    mask = ImageMask(np.flipud(np.asarray(disk.coverage(grid))), 3.2, center_mm=(-0.025, -0.025))
    # Sampled exactly at the image's pixel centres; float32 rounding of the coordinates only.
    np.testing.assert_allclose(mask.coverage(grid), disk.coverage(grid), atol=1e-5)


def test_image_mask_from_png_8_and_16_bit_and_rgb(tmp_path):
    grey = np.array([[0, 255], [51, 102]], dtype=np.uint8)
    iio.imwrite(tmp_path / "grey.png", grey)
    mask = ImageMask.from_file(tmp_path / "grey.png", 2.0)
    np.testing.assert_allclose(mask.transmission, [[0.0, 1.0], [0.2, 0.4]], atol=1e-6)
    assert mask.source == str(tmp_path / "grey.png")

    deep = np.array([[0, 65535], [13107, 0]], dtype=np.uint16)
    iio.imwrite(tmp_path / "deep.png", deep)
    np.testing.assert_allclose(
        ImageMask.from_file(tmp_path / "deep.png", 2.0).transmission, [[0, 1], [0.2, 0]], atol=1e-6
    )

    rgb = np.zeros((2, 2, 3), dtype=np.uint8)
    rgb[0, 0] = (255, 0, 0)
    rgb[1, 1] = (255, 255, 255)
    iio.imwrite(tmp_path / "rgb.png", rgb)
    t = np.asarray(ImageMask.from_file(tmp_path / "rgb.png", 2.0).transmission)
    np.testing.assert_allclose(t, [[0.2126, 0.0], [0.0, 1.0]], atol=1e-6)


# imageio, probing every plugin on the garbage file, imports its deprecated DICOM plugin.
@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_image_mask_file_errors(tmp_path):
    missing = tmp_path / "nope.png"
    with pytest.raises(InputDataError, match=r"nope.png"):
        ImageMask.from_file(missing, 1.0)

    garbage = tmp_path / "garbage.png"
    garbage.write_bytes(b"this is not a png")
    with pytest.raises(InputDataError, match=r"garbage.png"):
        ImageMask.from_file(garbage, 1.0)

    with_nan = np.ones((4, 4), dtype=np.float32)
    with_nan[1, 2] = np.nan
    np.save(tmp_path / "nan.npy", with_nan)
    with pytest.raises(InputDataError, match=r"nan.npy.*non-finite.*row 1, column 2"):
        ImageMask.from_file(tmp_path / "nan.npy", 1.0)

    iio.imwrite(tmp_path / "nan.tif", with_nan)
    with pytest.raises(InputDataError, match=r"nan.tif.*non-finite"):
        ImageMask.from_file(tmp_path / "nan.tif", 1.0)

    too_bright = np.full((3, 3), 1.5, dtype=np.float32)
    iio.imwrite(tmp_path / "bright.tif", too_bright)
    with pytest.raises(InputDataError, match=r"bright.tif.*1.5.*\[0, 1\]"):
        ImageMask.from_file(tmp_path / "bright.tif", 1.0)

    np.save(tmp_path / "cube.npy", np.zeros((3, 3, 5)))
    with pytest.raises(InputDataError, match=r"cube.npy.*2-D"):
        ImageMask.from_file(tmp_path / "cube.npy", 1.0)

    np.save(tmp_path / "ints.npy", np.zeros((3, 3), dtype=np.int32))
    with pytest.raises(InputDataError, match=r"ints.npy.*int32"):
        ImageMask.from_file(tmp_path / "ints.npy", 1.0)


# ---------------------------------------------------------------------------------------
# configuration


def test_every_kind_round_trips_through_config(tmp_path):
    iio.imwrite(tmp_path / "mask.png", np.full((4, 6), 200, dtype=np.uint8))
    tables = [
        {"kind": "disk", "diameter_mm": 4.0},
        {"kind": "disk", "diameter_mm": 4, "center_mm": [0.5, -1], "role": "block"},
        {"kind": "ellipse", "diameter_mm": 3.0, "ellipticity": 0.2, "rotation_deg": 30.0},
        {"kind": "polygon", "n_blades": 6, "diameter_mm": 2.0, "rounding": 0.5},
        {"kind": "capsule", "start_mm": [0, 0], "end_mm": [1.0, 2.0], "thickness_mm": 0.1},
        {"kind": "image", "path": "mask.png", "width_mm": 3.0, "rotation_deg": 5.0},
    ]
    assert {t["kind"] for t in tables} == set(SHAPE_KINDS)
    grid = ApertureGrid(32, 0.2)
    for i, table in enumerate(tables):
        shape = shape_from_config(table, f"model.shapes[{i}]", base_dir=tmp_path)
        written = shape_to_config(shape)
        for key, value in table.items():
            if key != "path":
                assert written[key] == (value if isinstance(value, str) else pytest.approx(value))
        again = shape_from_config(written, "again")
        assert type(again) is type(shape) and again.role == shape.role
        np.testing.assert_array_equal(again.coverage(grid), shape.coverage(grid))
    assert shape_to_config(shape_from_config(tables[0], "x"))["role"] == "open"
    assert shape_to_config(shape_from_config(tables[4], "x"))["role"] == "block"
    image = shape_from_config(tables[5], "x", base_dir=tmp_path)
    np.testing.assert_allclose(image.transmission, 200 / 255, atol=1e-6)


@pytest.mark.parametrize(
    ("table", "match"),
    [
        ({"kind": "hexagon", "diameter_mm": 4.0}, r"model.shapes\[0\].*hexagon.*disk, ellipse"),
        ({"diameter_mm": 4.0}, r"model.shapes\[0\].*kind"),
        (
            {"kind": "disk", "diamter_mm": 4.0},
            r"model.shapes\[0\].*'diamter_mm'.*valid keys.*diameter_mm.*center_mm",
        ),
        ({"kind": "polygon", "diameter_mm": 4.0}, r"model.shapes\[0\].*'n_blades'"),
        ({"kind": "disk", "diameter_mm": "4"}, r"model.shapes\[0\].diameter_mm.*number.*'4'"),
        ({"kind": "disk", "diameter_mm": True}, r"diameter_mm.*number"),
        ({"kind": "polygon", "n_blades": 6.5, "diameter_mm": 2.0}, r"n_blades.*integer.*6.5"),
        ({"kind": "disk", "diameter_mm": 4.0, "center_mm": [1.0]}, r"center_mm.*pair"),
        ({"kind": "disk", "diameter_mm": 4.0, "role": "opaque"}, r"role.*opaque.*open, block"),
        ("disk", r"model.shapes\[0\].*table"),
    ],
)
def test_config_errors(table, match):
    with pytest.raises(ConfigError, match=match):
        shape_from_config(table, "model.shapes[0]")


def test_config_range_and_file_errors_name_the_location(tmp_path):
    with pytest.raises(PhysicsRangeError, match=r"model.shapes\[2\].*diameter_mm.*-4"):
        shape_from_config({"kind": "disk", "diameter_mm": -4.0}, "model.shapes[2]")
    with pytest.raises(InputDataError, match=r"model.shapes\[1\].*missing.png"):
        shape_from_config(
            {"kind": "image", "path": "missing.png", "width_mm": 1.0}, "model.shapes[1]", tmp_path
        )
    with pytest.raises(ConfigError, match="no path"):
        shape_to_config(ImageMask(np.ones((2, 2)), 1.0))
