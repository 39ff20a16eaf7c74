"""Tests of the eye aperture (invglare.aperture.eye), its config reader
(invglare.config.eye) and local stamps (invglare.aperture.shapes.stamps).

Tolerances are stated in the test names / docstrings, with the measured errors beside them
(float32 unless a test says float64). Grids are 64-128 px to keep the file fast.
"""

from __future__ import annotations

import dataclasses
import itertools
import math

import equinox as eqx
import helpers
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from invglare._core.grids import ApertureGrid
from invglare.aperture import Capsule, Disk
from invglare.aperture.eye import (
    EYE_KEYS,
    EyeAperture,
    Eyelashes,
    Eyelids,
    Gratings,
    Particles,
    Pupil,
    daylight_eye,
    eye_to_config,
    lashed_daylight_eye,
    night_eye,
    relaxed_weights,
)
from invglare.aperture.shapes.stamps import (
    disks_log_transmission,
    polyline_log_transmission,
    segments_log_transmission,
    transmission_from_log,
    window_half_px,
)
from invglare.config.eye import eye_from_config
from invglare.errors import ConfigError, PhysicsRangeError
from invglare.optics.fraunhofer import fraunhofer_fft

KEY = jax.random.key(3)


def _small_eye(dtype=None) -> EyeAperture:
    """Every component, sized for a 64 px grid of 2.2 mm (pitch 34 um)."""
    return EyeAperture(
        pupil=Pupil(2.0, 0.05, 20.0, (0.03, -0.02)),
        lids=Eyelids(0.8, 0.9, 5.0, -3.0, 0.1),
        upper_lashes=Eyelashes(
            count=3.4,
            n_max=5,
            key=jax.random.fold_in(KEY, 1),
            lid="upper",
            mean_angle_deg=5.0,
            angular_spread_deg=10.0,
            spacing_jitter=0.5,
            thickness_mm=0.08,
            length_mm=1.5,
            curvature_per_mm=0.3,
            root_span_mm=2.0,
        ),
        lower_lashes=Eyelashes(
            count=2.0,
            n_max=2,
            key=jax.random.fold_in(KEY, 2),
            lid="lower",
            thickness_mm=0.06,
            length_mm=1.2,
            root_span_mm=1.5,
        ),
        particles=(
            Particles(
                count=6.6,
                n_max=8,
                key=jax.random.fold_in(KEY, 3),
                region="lens_nucleus",
                radius_mean_mm=0.04,
                radius_spread=0.3,
                region_radius_mm=1.0,
            ),
        ),
        gratings=Gratings(
            count=2.5,
            n_max=3,
            key=jax.random.fold_in(KEY, 4),
            spacing_mm=0.12,
            line_thickness_mm=0.05,
            line_length_mm=0.5,
            inner_radius_mm=0.3,
            outer_radius_mm=0.9,
            lines_per_grating=3,
        ),
    )


def _grid(npix=64, width=2.2) -> ApertureGrid:
    return ApertureGrid.from_width(npix, width)


# ---------------------------------------------------------------------------------------
# stamps


def test_stamped_disks_equal_full_image_disks_1e5():
    """Each stamp is the full-image Disk coverage; several disks (overlapping, partly or
    wholly off the grid, one at half weight) multiply as independent occluders."""
    grid = ApertureGrid(96, 0.01)
    centers = np.array([[0.0123, -0.0711], [0.2037, 0.1049], [0.2191, 0.1122], [-0.4731, 0.3]])
    centers = np.vstack([centers, [[0.9, -0.3], [-2.0, -2.0]]])  # off the grid's edge / far
    radii = np.array([0.05, 0.031, 0.02, 0.043, 0.07, 0.05])
    weights = np.array([1.0, 0.7, 1.0, 1.0, 1.0, 1.0])
    got = transmission_from_log(disks_log_transmission(grid, centers, radii, weights))
    expected = np.ones((96, 96))
    for c, r, w in zip(centers, radii, weights, strict=True):
        expected *= 1.0 - w * np.asarray(Disk(2 * r, c).coverage(grid))
    assert np.abs(np.asarray(got) - expected).max() < 1e-5  # measured 3.0e-6


def test_stamped_segments_and_straight_polyline_equal_capsules_1e5():
    grid = ApertureGrid(96, 0.01)
    starts = np.array([[0.0031, 0.0047], [-0.3, 0.2]])
    ends = np.array([[0.2013, 0.1326], [-0.1022, 0.2517]])
    thick = np.array([0.03, 0.015])
    got = transmission_from_log(segments_log_transmission(grid, starts, ends, thick, np.ones(2)))
    expected = np.ones((96, 96))
    for a, b, t in zip(starts, ends, thick, strict=True):
        expected *= 1.0 - np.asarray(Capsule(a, b, t).coverage(grid))
    assert np.abs(np.asarray(got) - expected).max() < 1e-5  # measured 2.7e-6
    # A straight polyline of 6 segments, each stamped on its own window, is one capsule.
    a, b = np.array([-0.3113, 0.2034]), np.array([0.2816, -0.1702])
    pts = (a + np.linspace(0.0, 1.0, 7)[:, None] * (b - a))[None]
    log_t = polyline_log_transmission(grid, pts, np.array([0.025]), np.ones(1), 12)
    expected = 1.0 - np.asarray(Capsule(a, b, 0.025).coverage(grid))
    # float32 rounding: interior segments are extended far past their window (measured 1.2e-5)
    assert np.abs(np.asarray(transmission_from_log(log_t)) - expected).max() < 3e-5


def _polyline_truth(pts: np.ndarray, half_width: float, npix: int, pitch: float, sub=24):
    """Per-pixel area of {distance to the polyline <= half_width}, by sub x sub samples."""
    c = (np.arange(npix) - npix // 2) * pitch
    o = ((np.arange(sub) + 0.5) / sub - 0.5) * pitch
    x = c[None, :, None, None] + o[None, None, None, :]
    y = c[:, None, None, None] + o[None, None, :, None]
    x, y = np.broadcast_arrays(x, y)
    dist = np.full(x.shape, np.inf)
    for a, b in itertools.pairwise(pts):
        u = b - a
        t = np.clip(((x - a[0]) * u[0] + (y - a[1]) * u[1]) / (u @ u), 0.0, 1.0)
        dist = np.minimum(dist, np.hypot(x - a[0] - t * u[0], y - a[1] - t * u[1]))
    return (dist <= half_width).mean(axis=(2, 3))


def test_curved_polyline_counts_each_pixel_once():
    """A bent lash (8 segments, 3 deg per joint) against the exact area of its round-joined
    outline: each pixel is claimed by one segment, so the joints are not counted twice.
    Max per-pixel error 0.015 (measured 9e-3, with 1/576 sampling steps), mean 2e-3."""
    grid = ApertureGrid(96, 0.01)
    s = np.linspace(0.0, 1.0, 9)[:, None]
    pts = np.array([-0.35, -0.2]) + s * np.array([0.7, 0.1]) + 0.3 * (s * 0.7) ** 2 * [0, 1]
    log_t = polyline_log_transmission(grid, pts[None], [0.04], [1], 10)
    coverage = 1.0 - np.asarray(transmission_from_log(log_t))
    truth = _polyline_truth(pts, 0.02, 96, 0.01)
    err = np.abs(coverage - truth)
    assert err.max() < 0.015
    assert err[(truth > 0) & (truth < 1)].mean() < 2e-3  # measured 9e-4
    caps = [np.asarray(Capsule(a, b, 0.04).coverage(grid)) for a, b in itertools.pairwise(pts)]
    product = 1.0 - np.prod([1.0 - c for c in caps], axis=0)
    assert np.abs(product - truth).max() > 0.1  # what independent segments would give


def test_window_half_px_and_traced_sizes():
    assert window_half_px(0.05, 0.01) == 7  # ceil(5 + 1.25)
    with pytest.raises(ConfigError, match="with_stamp_windows"):
        jax.jit(lambda r: window_half_px(r, 0.01))(0.05)


def test_particles_equal_product_of_individual_disks_1e5():
    grid = _grid(96, 2.2)
    p = Particles(count=12.3, n_max=16, key=KEY, radius_mean_mm=0.05, region_radius_mm=1.0)
    got = np.asarray(transmission_from_log(p.log_transmission(grid)))
    expected = np.ones((96, 96))
    for c, r, w in zip(p.centers_mm(), p.radii_mm(), p.weights(), strict=True):
        expected *= 1.0 - float(w) * np.asarray(Disk(2 * r, c).coverage(grid))
    assert np.abs(got - expected).max() < 1e-5  # measured 3.6e-6


def test_particle_regions_distribution():
    """Disk-uniform (cornea) vs ball-projected (nucleus): mean r / R is 2/3 vs 3 pi / 16."""
    n = 4000
    for region, mean in (("cornea", 2.0 / 3.0), ("vitreous", 3.0 * math.pi / 16.0)):
        p = Particles(count=n, n_max=n, key=KEY, region=region, region_radius_mm=2.0)
        r = np.linalg.norm(np.asarray(p.centers_mm()), axis=-1) / 2.0
        assert r.max() <= 1.0 + 1e-6
        assert abs(r.mean() - mean) < 0.02, region  # standard error ~0.004
    radii = np.asarray(Particles(count=n, n_max=n, key=KEY, radius_mean_mm=0.01).radii_mm())
    assert abs(radii.mean() / 0.01 - 1.0) < 0.03  # log-normal with the stated mean


# ---------------------------------------------------------------------------------------
# relaxed counts


def test_relaxed_weights_exact_at_integers():
    np.testing.assert_array_equal(np.asarray(relaxed_weights(3.0, 6)), [1, 1, 1, 0, 0, 0])
    w = np.asarray(relaxed_weights(3.25, 6))
    assert w[3] == pytest.approx(0.25**2 * (3 - 0.5)) and w[4] == 0.0


@pytest.mark.slow
def test_integer_count_is_the_smaller_pool():
    """count = k in a pool of n_max equals a pool of exactly k elements (weights 1)."""
    grid = _grid()
    eye = _small_eye()
    p = eye.particles[0]
    big = eqx.tree_at(lambda q: q.count, p, 5.0)
    small = Particles(
        count=5.0,
        n_max=5,
        key=p.key,
        region=p.region,
        radius_mean_mm=0.04,
        radius_spread=0.3,
        region_radius_mm=1.0,
    )
    np.testing.assert_allclose(big.log_transmission(grid), small.log_transmission(grid), atol=1e-6)
    lashes = eqx.tree_at(lambda q: q.count, eye.upper_lashes, 3.0)
    few = Eyelashes(
        count=3.0,
        n_max=3,
        key=lashes.key,
        mean_angle_deg=5.0,
        thickness_mm=0.08,
        length_mm=1.5,
        curvature_per_mm=0.3,
        root_span_mm=2.0,
    )
    a = lashes.log_transmission(grid, eye.lids)
    b = few.log_transmission(grid, eye.lids)
    np.testing.assert_allclose(a, b, atol=1e-6)
    g = eqx.tree_at(lambda q: q.count, eye.gratings, 2.0)
    g2 = Gratings(
        count=2.0,
        n_max=2,
        key=g.key,
        spacing_mm=0.12,
        line_thickness_mm=0.05,
        line_length_mm=0.5,
        inner_radius_mm=0.3,
        outer_radius_mm=0.9,
        lines_per_grating=3,
    )
    np.testing.assert_allclose(g.log_transmission(grid), g2.log_transmission(grid), atol=1e-6)


def test_count_between_integers_blends_one_element_1e5():
    """Particles at count k + f: element k has weight s(f), so T = T_k + s(f) (T_k+1 - T_k)."""
    grid = _grid()
    p = _small_eye().particles[0]

    def t(count):
        return np.asarray(
            transmission_from_log(eqx.tree_at(lambda q: q.count, p, count).log_transmission(grid))
        )

    t4, t5 = t(4.0), t(5.0)
    assert np.abs(t5 - t4).max() > 0.5  # the fifth particle is on the grid
    for f in (0.1, 0.5, 0.8):
        s = f * f * (3 - 2 * f)
        assert np.abs(t(4.0 + f) - (t4 + s * (t5 - t4))).max() < 1e-5  # measured 6e-8


# ---------------------------------------------------------------------------------------
# lids


def test_blink_closes_the_pupil():
    grid = _grid()
    eye = _small_eye()
    # Openings 0 with the margins meeting (equal tilts; unequal ones leave a wedge open).
    closed = eqx.tree_at(
        lambda e: (e.lids.upper_opening_mm, e.lids.lower_opening_mm, e.lids.lower_tilt_deg),
        eye,
        (jnp.asarray(0.0), jnp.asarray(0.0), eye.lids.upper_tilt_deg),
    )
    pupil_area = float(jnp.sum(eye.pupil.coverage(grid)))
    assert float(jnp.sum(closed.transmission(grid))) < 1e-6 * pupil_area  # measured 0
    # Without curvature and tilt too (two straight edges meeting on a pixel row).
    flat = EyeAperture(Pupil(2.0), lids=Eyelids(0.0, 0.0, 0.0, 0.0, 0.0))
    assert float(jnp.sum(flat.transmission(grid))) < 1e-6 * pupil_area
    # A squint (partial openings) leaves the band between the margins.
    squint = EyeAperture(Pupil(2.0), lids=Eyelids(0.3, 0.2, 0.0, 0.0, 0.0))
    band = float(jnp.sum(squint.transmission(grid))) * float(grid.pitch_mm) ** 2

    def chord_area(y):  # area of the unit disk below height y, up to a constant
        return y * math.sqrt(1.0 - y * y) + math.asin(y)

    expected = chord_area(0.3) - chord_area(-0.2)
    assert band == pytest.approx(expected, rel=2e-3)  # measured 3e-4


def test_lid_tilt_rotates_the_edge():
    """Open height of each column is opening / cos(tilt) + x tan(tilt): a straight margin
    (curvature 0) turned by the tilt. Slope to 1e-3, offset to 1e-3 mm."""
    grid = _grid(128, 4.0)
    pitch = float(grid.pitch_mm)
    y = np.asarray(grid.coords_mm())
    for tilt in (0.0, 12.0, -20.0):
        lids = Eyelids(0.7, 50.0, tilt, 0.0, 0.0)
        t = np.asarray(lids.transmission(grid))
        height = t.sum(axis=0) * pitch + y[0] - 0.5 * pitch  # margin height per column
        x = np.asarray(grid.coords_mm())
        keep = np.abs(x) < 1.2
        slope, offset = np.polyfit(x[keep], height[keep], 1)
        assert slope == pytest.approx(math.tan(math.radians(tilt)), abs=1e-3)
        assert offset == pytest.approx(0.7 / math.cos(math.radians(tilt)), abs=1e-3)


def test_obstacle_shift_translates_lids_and_lashes():
    """A shift of whole pixels moves t_o by that many pixels (1e-5 away from the edges)."""
    grid = _grid()
    eye = _small_eye()
    pitch = float(grid.pitch_mm)
    base = np.asarray(eye.obstacle_transmission(grid))
    moved = np.asarray(eye.obstacle_transmission(grid, (3 * pitch, -2 * pitch)))
    np.testing.assert_allclose(
        moved[8:-8, 8:-8], np.roll(base, (-2, 3), (0, 1))[8:-8, 8:-8], atol=1e-5
    )  # measured 4e-7


# ---------------------------------------------------------------------------------------
# lashes


def _streak_angle_deg(psf: np.ndarray, r_min: float, r_max: float) -> float:
    """Angle (deg, mod 180) of the strongest 1-degree bin of energy in an annulus."""
    n = psf.shape[0]
    v, u = np.mgrid[:n, :n] - n // 2
    r = np.hypot(u, v)
    ring = (r >= r_min) & (r <= r_max)
    ang = np.degrees(np.arctan2(v[ring], u[ring])) % 180.0
    hist, edges = np.histogram(ang, bins=180, range=(0, 180), weights=psf[ring])
    return float(edges[np.argmax(hist)] + 0.5)


@pytest.mark.parametrize("mean_angle_deg", [30.0, -20.0])
def test_single_lash_streak_is_perpendicular_to_the_lash(mean_angle_deg):
    """Lash direction -90 + mean angle (pointing down from the upper lid); the PSF's energy
    peaks at 90 deg from it, within 2 deg (measured 0.5)."""
    grid = _grid(128, 3.2)
    lash = Eyelashes(
        count=1.0,
        n_max=1,
        key=KEY,
        mean_angle_deg=mean_angle_deg,
        angular_spread_deg=0.0,
        spacing_jitter=0.0,
        thickness_mm=0.06,
        length_mm=6.0,
        root_span_mm=1.0,
        length_spread=0.0,
        thickness_spread=0.0,
    )
    eye = EyeAperture(Pupil(3.0), lids=Eyelids(2.5, 10.0, 0.0, 0.0, 0.0), upper_lashes=lash)
    psf, _ = fraunhofer_fft(eye.transmission(grid), grid, 550.0, 512)
    lash_dir = -90.0 + mean_angle_deg
    expected = (lash_dir + 90.0) % 180.0
    got = _streak_angle_deg(np.asarray(psf), 15, 200)
    diff = abs((got - expected + 90.0) % 180.0 - 90.0)
    assert diff < 2.0, (got, expected)
    assert float(jnp.sum(eye.transmission(grid))) < 0.995 * float(jnp.sum(eye.pupil.coverage(grid)))


def test_lash_layout_follows_the_lid():
    """Roots sit on the margin; with no spread a lash leaves along the margin's normal."""
    lids = Eyelids(1.0, 1.0, 15.0, 0.0, 0.2)
    lash = Eyelashes(count=4.0, n_max=4, key=KEY, angular_spread_deg=0.0, curvature_per_mm=0.0)
    pts, _, _ = lash.polylines(lids)
    roots, normals = lids.margin("upper", np.linspace(-3, 3, 4))
    for i in range(4):
        d = np.asarray(pts[i, -1] - pts[i, 0])
        root = np.asarray(pts[i, 0])
        # on the margin: the tilted parabola's equation holds
        c, s = math.cos(math.radians(15)), math.sin(math.radians(15))
        x_l, y_l = c * root[0] + s * root[1], -s * root[0] + c * root[1]
        assert y_l == pytest.approx(1.0 - 0.1 * x_l**2, abs=1e-5)
        n = np.array([-0.2 * x_l, -1.0]) / math.hypot(0.2 * x_l, 1.0)
        n = np.array([c * n[0] - s * n[1], s * n[0] + c * n[1]])
        np.testing.assert_allclose(d / np.linalg.norm(d), n, atol=1e-5)
    assert normals.shape == roots.shape == (4, 2)


# ---------------------------------------------------------------------------------------
# gradients (float64)


def _float_leaves(eye) -> list[tuple[str, int, int | None, float]]:
    """(path, leaf number, index within the leaf or None, value) of every float parameter."""
    params, _ = eqx.partition(eye, eqx.is_inexact_array)
    out = []
    for n, (path, leaf) in enumerate(jax.tree_util.tree_flatten_with_path(params)[0]):
        name = jax.tree_util.keystr(path).lstrip(".")
        values = np.asarray(leaf)
        if values.ndim == 0:
            out.append((name, n, None, float(values)))
        else:
            out += [(f"{name}[{j}]", n, j, float(v)) for j, v in enumerate(values)]
    return out


def _with_leaf(eye, n: int, index: int | None, x):
    """`eye` with its `n`-th float leaf (element `index` of it, if given) set to `x`."""
    params, static = eqx.partition(eye, eqx.is_inexact_array)
    leaves, treedef = jax.tree_util.tree_flatten(params)
    leaves[n] = x if index is None else leaves[n].at[index].set(x)
    return eqx.combine(jax.tree_util.tree_unflatten(treedef, leaves), static)


# Relative steps (of max(|x|, 0.1)) where the default 1e-5 would straddle one of the
# rasteriser's kinks (at 1.1e-5 mm from the lash length here): a kink is not a derivative
# error, and a step that straddles it does not converge.
_FD_STEP = {"upper_lashes.length_mm": 5e-6}


@pytest.mark.slow
def test_every_float_leaf_gradient_converges_to_finite_differences_float64():
    """d/dx sum(weights * transmission) by autodiff for every float parameter of the eye
    (pupil, lids, upper lashes, particles, gratings: 30 in all) against central
    differences at two steps, 1e-5 and 5e-6 of the parameter's scale: the finer one
    within rtol 1e-5 (+ 1e-6 absolute, rounding), and halving the step at least halves
    the discrepancy (measured: about 4x where the discrepancy is above rounding, e.g.
    1.7e-6 -> 4.4e-7 relative for the gratings' inner radius). The lower lashes are left
    out (the same class as the upper ones, and a bigger program to compile)."""
    with helpers.x64():
        grid = _grid()
        eye = dataclasses.replace(_small_eye(), lower_lashes=None).with_stamp_windows(grid)
        # The converters make weakly typed leaves and the differences set strongly typed
        # ones: the jitted loss would compile again for every mix of the two.
        eye = jax.tree.map(lambda v: v.astype(v.dtype) if eqx.is_inexact_array(v) else v, eye)
        weights = jnp.asarray(np.random.default_rng(0).uniform(size=(64, 64)))
        loss = eqx.filter_jit(lambda e: jnp.sum(weights * e.transmission(grid)))
        # One gradient program gives every derivative; each difference is two calls of
        # one compiled forward program.
        grads = _float_leaves(eqx.filter_grad(loss)(eye))
        leaves = _float_leaves(eye)
        assert len(leaves) == 30 and [g[0] for g in grads] == [p[0] for p in leaves]
        failures = []
        for (path, n, index, x0), (*_, ad) in zip(leaves, grads, strict=True):
            step = _FD_STEP.get(path, 1e-5) * max(abs(x0), 0.1)
            try:
                helpers.assert_fd_converges(
                    lambda x, n=n, index=index: loss(_with_leaf(eye, n, index, x)),
                    x0,
                    ad,
                    step,
                    rtol=1e-5,
                    atol=1e-6,
                )
                assert abs(ad) > 0.1, f"{path} barely moves the transmission (d = {ad:g})"
            except AssertionError as err:
                failures.append(f"{path}: {err}")
        assert not failures, "\n".join(failures)


# ---------------------------------------------------------------------------------------
# transformations


@pytest.mark.slow
def test_jit_equals_eager_and_needs_fixed_windows():
    grid = _grid()
    eye = _small_eye()
    eager = np.asarray(eye.transmission(grid))
    fixed = eye.with_stamp_windows(grid)  # larger windows, same elements
    np.testing.assert_allclose(np.asarray(fixed.transmission(grid)), eager, atol=1e-6)
    # the grid is traced too: the fixed windows carry the static sizes
    jitted = eqx.filter_jit(lambda e, g: e.transmission(g))(fixed, grid)
    np.testing.assert_allclose(np.asarray(jitted), eager, atol=1e-6)
    with pytest.raises(ConfigError, match="with_stamp_windows"):
        eqx.filter_jit(lambda e: e.transmission(grid))(eye)


@pytest.mark.slow
def test_vmap_over_pupil_diameters_equals_loop():
    grid = _grid()
    eye = _small_eye()
    diameters = jnp.asarray([1.2, 1.7, 2.05])

    def t(d):
        return eqx.tree_at(lambda e: e.pupil.diameter_mm, eye, d).transmission(grid)

    batched = np.asarray(jax.vmap(t)(diameters))
    for i, d in enumerate(diameters):
        # A weakly typed diameter, like the eye's own: the loop reuses the eye's compiled
        # transmission (shared with the other tests) instead of compiling another.
        single = np.asarray(t(jnp.asarray(float(d))))
        # float32 rounding differs between the batched and unbatched programs (measured 2e-6)
        np.testing.assert_allclose(batched[i], single, atol=1e-5)


def test_vmap_over_obstacle_shifts_equals_loop():
    grid = _grid()
    eye = _small_eye()
    shifts = jnp.asarray([[0.0, 0.0], [0.05, -0.1], [-0.2, 0.03]])
    batched = np.asarray(jax.vmap(lambda s: eye.obstacle_transmission(grid, s))(shifts))
    for i, s in enumerate(shifts):
        np.testing.assert_allclose(
            batched[i], np.asarray(eye.obstacle_transmission(grid, s)), atol=1e-6
        )


# ---------------------------------------------------------------------------------------
# bad input

_BAD = [
    (lambda: Pupil(-3.0), PhysicsRangeError, "-3"),
    (lambda: Pupil(3.0, ellipticity=1.0), PhysicsRangeError, "ellipticity"),
    (lambda: Eyelids(upper_opening_mm=-0.5), PhysicsRangeError, "-0.5"),
    (lambda: Eyelids(curvature_per_mm=-0.1), PhysicsRangeError, "-0.1"),
    (lambda: Eyelashes(count=-1.0, n_max=4, key=KEY), PhysicsRangeError, "-1"),
    (lambda: Eyelashes(count=5.0, n_max=4, key=KEY), PhysicsRangeError, "5"),
    (
        lambda: Eyelashes(count=2.0, n_max=4, key=KEY, thickness_mm=-0.02),
        PhysicsRangeError,
        "-0.02",
    ),
    (lambda: Eyelashes(count=2.0, n_max=4, key=KEY, length_mm=0.0), PhysicsRangeError, "length_mm"),
    (lambda: Eyelashes(count=2.0, n_max=4, key=KEY, lid="middle"), ConfigError, "middle"),
    (lambda: Eyelashes(count=2.0, n_max=0, key=KEY), PhysicsRangeError, "n_max"),
    (lambda: Eyelashes(count=2.0, n_max=4.0, key=KEY), ConfigError, "n_max"),
    (lambda: Particles(count=3.0, n_max=2, key=KEY), PhysicsRangeError, "3"),
    (
        lambda: Particles(count=1.0, n_max=2, key=KEY, radius_mean_mm=-0.01),
        PhysicsRangeError,
        "-0.01",
    ),
    (lambda: Particles(count=1.0, n_max=2, key=KEY, region="retina"), ConfigError, "retina"),
    (
        lambda: Gratings(count=1.0, n_max=2, key=KEY, inner_radius_mm=3.0, outer_radius_mm=2.0),
        PhysicsRangeError,
        "3",
    ),
    (
        lambda: Gratings(count=1.0, n_max=2, key=KEY, spacing_mm=0.0),
        PhysicsRangeError,
        "spacing_mm",
    ),
    (
        lambda: Gratings(count=1.0, n_max=2, key=KEY, line_thickness_mm=-1e-3),
        PhysicsRangeError,
        "-0.001",
    ),
    (
        lambda: EyeAperture(Pupil(3.0), upper_lashes=Eyelashes(count=1.0, n_max=1, key=KEY)),
        ConfigError,
        "lids",
    ),
    (
        lambda: EyeAperture(
            Pupil(3.0),
            lids=Eyelids(),
            upper_lashes=Eyelashes(count=1.0, n_max=1, key=KEY, lid="lower"),
        ),
        ConfigError,
        "lower",
    ),
    (lambda: Particles(count=1.0, n_max=2, key="seed"), ConfigError, "key"),
]


@pytest.mark.parametrize("make, error, text", _BAD)
def test_bad_input_raises_documented_error(make, error, text):
    with pytest.raises(error) as info:
        make()
    assert text in str(info.value)


def test_config_unknown_key_lists_valid_keys():
    with pytest.raises(ConfigError) as info:
        eye_from_config({"pupil": {"diameter_mm": 3.0, "diamter": 1.0}}, "model.eye")
    msg = str(info.value)
    assert "model.eye.pupil" in msg and "'diamter'" in msg and "diameter_mm" in msg
    with pytest.raises(ConfigError) as info:
        eye_from_config({"pupil": {"diameter_mm": 3.0}, "lashes": {}}, "model.eye")
    assert "'lashes'" in str(info.value) and all(k in str(info.value) for k in EYE_KEYS)
    with pytest.raises(ConfigError, match="count"):
        eye_from_config({"pupil": {"diameter_mm": 3.0}, "particles": [{"region": "cornea"}]})
    with pytest.raises(ConfigError, match="must be a number"):
        eye_from_config({"pupil": {"diameter_mm": "3 mm"}})
    with pytest.raises(PhysicsRangeError, match=r"eye\.pupil.*-2"):
        eye_from_config({"pupil": {"diameter_mm": -2.0}})
    with pytest.raises(ConfigError, match="pupil"):
        eye_from_config({"lids": {}})


def test_config_names_bad_key_data_and_particle_lists():
    pupil = {"diameter_mm": 3.0}
    lashes = {"count": 2, "length_mm": 1.0}
    for bad in ([1, -2], [1.5, 2], [], "7"):
        with pytest.raises(ConfigError, match=r"lashes_upper\.key_data.*uint32"):
            eye_from_config(
                {"pupil": pupil, "lids": {}, "lashes_upper": {**lashes, "key_data": bad}}
            )
    with pytest.raises(ConfigError, match=r"lashes_upper\.key_data = \[1, 2, 3\].*jax\.random"):
        eye_from_config(
            {"pupil": pupil, "lids": {}, "lashes_upper": {**lashes, "key_data": [1, 2, 3]}}
        )
    with pytest.raises(ConfigError, match=r"model\.eye\.particles must be an array of tables"):
        eye_from_config({"pupil": pupil, "particles": 3}, "model.eye")
    with pytest.raises(ConfigError, match=r"model\.eye\.particles\[1\]\] must be a table"):
        eye_from_config(
            {"pupil": pupil, "particles": [{"region": "cornea", "count": 1}, 2]}, "model.eye"
        )
    with pytest.raises(ConfigError, match=r"pupil\.decentration_mm must be a pair of numbers"):
        eye_from_config({"pupil": {**pupil, "decentration_mm": [0.1, "0"]}})
    one = eye_from_config({"pupil": pupil, "particles": {"region": "cornea", "count": 1}})
    assert len(one.particles) == 1 and one.particles[0].n_max == 1


def test_config_round_trip_gives_the_same_transmission():
    grid = _grid()
    eye = _small_eye()
    table = eye_to_config(eye)
    again = eye_from_config(table)
    np.testing.assert_array_equal(
        np.asarray(again.transmission(grid)), np.asarray(eye.transmission(grid))
    )
    assert eye_to_config(again) == table
    # A seeded config is reproducible and keys differ between components.
    seeded = {
        "seed": 5,
        "pupil": {"diameter_mm": 2.0},
        "lids": {"upper_opening_mm": 0.8},
        "lashes_upper": {"count": 3, "length_mm": 1.5},
        "particles": [{"region": "cornea", "count": 4, "radius_mean_mm": 0.05}],
    }
    a, b = eye_from_config(seeded), eye_from_config(seeded)
    np.testing.assert_array_equal(
        np.asarray(a.transmission(grid)), np.asarray(b.transmission(grid))
    )
    assert a.upper_lashes.n_max == 3


def test_presets_have_their_documented_values():
    day, night = lashed_daylight_eye(KEY), night_eye(KEY)
    with pytest.warns(DeprecationWarning, match="lashed_daylight_eye"):
        old_name = daylight_eye(KEY)
    assert eye_to_config(old_name) == eye_to_config(day)
    assert float(day.pupil.diameter_mm) == 3.0 and float(night.pupil.diameter_mm) == 7.0
    assert [p.region for p in night.particles] == ["lens_nucleus", "vitreous"]
    assert float(night.particles[0].count) == 750.0 and float(night.gratings.count) == 200.0
    assert day.gratings is None and float(day.upper_lashes.count) == 40.0
    assert day.extent_mm() == pytest.approx(3.0)
    table = eye_to_config(night)
    assert eye_to_config(eye_from_config(table)) == table


# ---------------------------------------------------------------------------------------
# pupil decentration and the gratings' annulus


def test_decentred_pupil_is_the_centred_one_shifted():
    """A decentration of a whole number of pixels shifts the pupil's raster by them."""
    grid = _grid()
    pitch = float(grid.pitch_mm)
    centred = np.asarray(Pupil(1.2).coverage(grid))
    moved = np.asarray(Pupil(1.2, decentration_mm=(3 * pitch, -2 * pitch)).coverage(grid))
    # float32 coordinates: the edge pixels agree to a few 1e-6
    np.testing.assert_allclose(moved, np.roll(centred, (-2, 3), axis=(0, 1)), atol=1e-5)
    assert not np.allclose(moved, centred, atol=1e-3)


def test_grating_patches_fill_their_annulus_uniformly_in_area():
    gratings = Gratings(count=400.0, n_max=400, key=KEY, inner_radius_mm=0.6, outer_radius_mm=1.3)
    starts, ends, _ = gratings.lines()
    # A patch's centre is the mean of its lines' midpoints.
    mids = 0.5 * (np.asarray(starts) + np.asarray(ends))
    centres = mids.reshape(400, gratings.lines_per_grating, 2).mean(axis=1)
    rho = np.hypot(centres[:, 0], centres[:, 1])
    assert rho.min() >= 0.6 - 1e-6 and rho.max() <= 1.3 + 1e-6
    # Uniform in area: half the patches inside the radius that halves the annulus's area.
    half = math.sqrt(0.5 * (0.6**2 + 1.3**2))
    assert abs(np.mean(rho < half) - 0.5) < 0.08


@pytest.mark.slow
def test_stamp_windows_also_hold_the_largest_of_other_values():
    """`also=`: windows sized for the largest element over several parameter values.

    With them, the eye at the larger sizes transmits exactly what it does with generous
    windows (1e-12); the windows of the current sizes alone (headroom 1) cut its elements,
    which is what the comparison would catch.
    """
    with helpers.x64():
        _check_stamp_windows_also()


def _check_stamp_windows_also():
    grid = _grid()
    eye = _small_eye()

    def grown(e):
        e = eqx.tree_at(lambda a: a.upper_lashes.length_mm, e, 2.0 * e.upper_lashes.length_mm)
        e = eqx.tree_at(
            lambda a: a.particles[0].radius_mean_mm, e, 2.0 * e.particles[0].radius_mean_mm
        )
        return eqx.tree_at(lambda a: a.gratings.line_length_mm, e, 1.6 * e.gratings.line_length_mm)

    big = grown(eye)
    fitted = eye.with_stamp_windows(grid, headroom=1.0, also=[big])
    tight = eye.with_stamp_windows(grid, headroom=1.0)
    generous = big.with_stamp_windows(grid, headroom=3.0)
    for name in ("upper_lashes", "gratings"):
        assert getattr(fitted, name).stamp_half_px > getattr(tight, name).stamp_half_px
    assert fitted.particles[0].stamp_half_px > tight.particles[0].stamp_half_px
    # The current sizes are held too: the larger of the two, slot by slot.
    assert fitted.lower_lashes.stamp_half_px == tight.lower_lashes.stamp_half_px
    expected = np.asarray(generous.transmission(grid))
    np.testing.assert_allclose(np.asarray(grown(fitted).transmission(grid)), expected, atol=1e-12)
    assert np.max(np.abs(np.asarray(grown(tight).transmission(grid)) - expected)) > 1e-3
    # At the current sizes, tighter windows change nothing: against the generous windows
    # (the grown eye's at headroom 3, which `also` gives the current eye: the windows, and
    # so the compiled program, of `generous` rather than a fourth window layout).
    roomy = eye.with_stamp_windows(grid, headroom=3.0, also=[big])
    assert all(
        getattr(roomy, name).stamp_half_px > getattr(tight, name).stamp_half_px
        for name in ("upper_lashes", "lower_lashes", "gratings")
    )
    np.testing.assert_allclose(
        np.asarray(tight.transmission(grid)), np.asarray(roomy.transmission(grid)), atol=1e-12
    )
    with pytest.raises(ConfigError, match="same eye"):
        eye.with_stamp_windows(grid, also=[dataclasses.replace(eye, particles=())])
