"""Camera apertures: diaphragm streaks, grating orders, f-number, gradients, jit/vmap, configs."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import assert_grad_converges, x64
from scipy.ndimage import map_coordinates

from invglare._core.grids import ApertureGrid
from invglare.aperture.camera import (
    CameraAperture,
    CrossScreen,
    Diaphragm,
    Dust,
    camera_to_config,
    polygon_area_factor,
)
from invglare.config.camera import camera_from_config
from invglare.errors import ConfigError, PhysicsRangeError
from invglare.optics.propagator import make_propagator

LAMBDA_NM = 550.0


def fft_psf(camera, npix=256, aperture_npix=128):
    """Unit-energy PSF of the camera's whole aperture at 550 nm on the FFT's native grid."""
    window = camera.extent_mm() * aperture_npix / (aperture_npix - 4)
    prop = make_propagator(
        window_mm=window,
        focal_length_mm=50.0,
        fft_wavelength_nm=LAMBDA_NM,
        shortest_wavelength_nm=LAMBDA_NM,
        npix=npix,
        aperture_npix=aperture_npix,
    )
    return np.asarray(prop(camera.transmission(prop.grid), LAMBDA_NM)), prop


def angular_energy(psf, r_min, r_max, step_deg=0.25):
    """Energy against direction (deg, from +x towards +y = rows) in an annulus (px).

    The PSF is sampled on a polar grid (bilinear) and weighted by r² so that the
    ~1/r² fall-off along a streak does not favour the inner radii.
    """
    c = psf.shape[0] // 2
    angles = np.arange(0.0, 360.0, step_deg)
    radii = np.arange(r_min, r_max, 0.5)
    a, r = np.meshgrid(np.deg2rad(angles), radii, indexing="ij")
    values = map_coordinates(psf, [c + r * np.sin(a), c + r * np.cos(a)], order=1)
    return angles, (values * r**2).sum(axis=1)


def peaks(profile, fraction=0.1):
    """Indices of circular local maxima above `fraction` of the largest."""
    top = profile.max()
    prev, nxt = np.roll(profile, 1), np.roll(profile, -1)
    return np.flatnonzero((profile >= prev) & (profile > nxt) & (profile > fraction * top))


def circular_distance_deg(a, b):
    return np.abs((np.asarray(a) - np.asarray(b) + 180.0) % 360.0 - 180.0)


# ------------------------------------------------------------------------------ physics


@pytest.mark.parametrize("n_blades", [5, 6, 7, 8])
def test_blade_streaks_count_and_directions(n_blades):
    """2n streaks for odd n, n for even n, each along a blade normal (within 2 deg)."""
    stop = Diaphragm(n_blades, f_number=8.0, focal_length_mm=50.0, rotation_deg=7.0)
    psf, _ = fft_psf(CameraAperture(stop))
    angles, energy = angular_energy(psf, 30, 110)
    found = angles[peaks(energy)]
    normals = np.asarray(stop.blade_normal_angles_deg())
    expected = np.unique(np.round(np.concatenate([normals, normals + 180.0]) % 360.0, 6))
    assert len(expected) == (2 * n_blades if n_blades % 2 else n_blades)
    assert len(found) == len(expected), (found, expected)
    for angle in expected:
        assert circular_distance_deg(found, angle).min() < 2.0, (angle, found)


def test_single_grating_orders_at_grating_equation_angles():
    """Lines of spacing S diffract into orders at sin(theta_m) = m lambda / S (within 0.5 px)."""
    spacing = 0.25
    camera = CameraAperture(
        Diaphragm(6, f_number=8.0, focal_length_mm=32.0, rounding=1.0),
        filter=CrossScreen((90.0,), spacing_mm=spacing, duty_cycle=0.3, line_offset_mm=0.03),
    )
    psf, prop = fft_psf(camera)
    c = psf.shape[0] // 2
    scale = float(prop.output.pixel_scale_rad)
    row = psf[c]  # vertical lines: the orders lie along x
    for m in (-3, -2, -1, 1, 2, 3):
        expected_px = math.asin(m * LAMBDA_NM * 1e-6 / spacing) / scale
        k = c + round(expected_px)
        k = k - 2 + int(np.argmax(row[k - 2 : k + 3]))
        a, b, d = row[k - 1 : k + 2]
        found_px = k - c + 0.5 * (a - d) / (a - 2 * b + d)
        assert abs(found_px - expected_px) < 0.5, (m, found_px, expected_px)
        assert row[k] > 1e-3 * row[c]  # a real order, not a ring of the Airy pattern
        assert np.argmax(psf[:, k]) == c  # and on the x axis


def test_two_line_sets_give_a_cross():
    """Lines at 0 and 90 deg: the glare energy lies along the two axes, not the diagonals."""
    camera = CameraAperture(
        Diaphragm(8, f_number=8.0, focal_length_mm=32.0, rounding=1.0),
        filter=CrossScreen((0.0, 90.0), spacing_mm=0.25, duty_cycle=0.2),
    )
    psf, _ = fft_psf(camera)
    angles, energy = angular_energy(psf, 20, 110)
    found = angles[peaks(energy, 0.05)]
    assert len(found) == 4
    for axis in (0.0, 90.0, 180.0, 270.0):
        assert circular_distance_deg(found, axis).min() < 1.0
    # The diagonals only hold the mixed orders (m, n), weaker by |c_1 / c_0|² ~ 0.055 here.
    diagonal = energy[np.isin(angles, [45.0, 135.0, 225.0, 315.0])]
    assert diagonal.max() < 0.1 * energy.max()


# ------------------------------------------------------------------------------ geometry


@pytest.mark.parametrize(("n_blades", "rounding"), [(5, 0.0), (6, 0.4), (8, 1.0)])
def test_f_number_sets_equal_area_diameter(n_blades, rounding):
    stop = Diaphragm(n_blades, f_number=4.0, focal_length_mm=18.0, rounding=rounding)
    assert float(stop.diameter_mm()) == pytest.approx(4.5, rel=1e-6)
    grid = ApertureGrid.from_width(256, 1.05 * CameraAperture(stop).extent_mm())
    area = float(stop.coverage(grid).sum() * grid.pitch_mm**2)
    # The rasterised opening has the area of the 4.5 mm circle (corner pixels ~1e-4).
    assert area == pytest.approx(math.pi / 4 * 4.5**2, rel=2e-4)


def test_area_factor_closed_forms():
    assert float(polygon_area_factor(6, 0.0)) == pytest.approx(1.5 * math.sqrt(3), rel=1e-6)
    assert float(polygon_area_factor(4, 0.0)) == pytest.approx(2.0, rel=1e-6)
    for n in (3, 5, 9):
        assert float(polygon_area_factor(n, 1.0)) == pytest.approx(math.pi, rel=1e-6)
    circle = Diaphragm(5, 2.0, 10.0, rounding=1.0)
    assert float(circle.circumscribed_diameter_mm()) == pytest.approx(5.0, rel=1e-6)


def test_cross_screen_open_fraction_and_shift():
    grid = ApertureGrid.from_width(200, 4.0)  # 20 um pitch; 0.2 mm lines: 20 whole periods
    single = CrossScreen((30.0,), spacing_mm=0.2, duty_cycle=0.23)
    # Any line direction: the open fraction over many periods is 1 - duty (edge rows aside).
    assert float(single.transmission(grid).mean()) == pytest.approx(0.77, abs=3e-3)
    # A thin line (0.3 px wide) keeps its area: the coverage is anti-aliased, not thresholded.
    thin = CrossScreen((90.0,), spacing_mm=0.2, duty_cycle=0.03)
    assert float(1.0 - thin.transmission(grid).mean()) == pytest.approx(0.03, rel=1e-3)
    # Shifting the screen by s moves its lines by s along their normal.
    shift = jnp.array([0.013, -0.041])
    normal = np.array([-math.sin(math.radians(30.0)), math.cos(math.radians(30.0))])
    moved = eqx.tree_at(lambda s: s.line_offset_mm, single, float(normal @ np.asarray(shift)))
    np.testing.assert_allclose(
        single.transmission(grid, shift), moved.transmission(grid), atol=2e-5
    )


def test_dust_density_and_determinism():
    grid = ApertureGrid.from_width(256, 20.0)
    covered = []
    for density in (0.05, 0.3, 0.6):
        c = Dust(density, opacity=1.0, feature_size_mm=0.4, key=11).coverage(grid)
        covered.append(float(jnp.mean(c > 0.5)))
    # The threshold is the normal quantile of 1 - density, and value noise is a little
    # lighter-tailed than a normal: measured 0.0534, 0.3334, 0.6126 (key 11), and over
    # keys 11-13 deviations of 2 to 11 %, so 15 % relative (an atol of 0.05 would accept
    # twice the density at 0.05).
    np.testing.assert_allclose(covered, [0.05, 0.3, 0.6], rtol=0.15)
    a = Dust(0.2, 0.7, 0.4, key=3).coverage(grid)
    b = Dust(0.2, 0.7, 0.4, key=jax.random.key(3)).coverage(grid)
    np.testing.assert_array_equal(a, b)
    assert float(jnp.max(a)) <= 0.7 + 1e-6
    assert float(jnp.abs(a - Dust(0.2, 0.7, 0.4, key=4).coverage(grid)).mean()) > 0.05


def test_dust_is_on_the_pupil_and_filter_is_the_obstacle():
    stop = Diaphragm(6, 4.0, 16.0)
    camera = CameraAperture(
        stop, filter=CrossScreen((0.0,), 0.3, 0.2), dust=Dust(0.3, 0.9, 0.5, key=1)
    )
    grid = ApertureGrid.from_width(64, 1.05 * camera.extent_mm())
    bare = stop.coverage(grid)
    pupil = camera.pupil_transmission(grid)
    assert float(jnp.sum(pupil)) < 0.9 * float(jnp.sum(bare))
    np.testing.assert_allclose(
        camera.transmission(grid), pupil * camera.filter.transmission(grid), atol=1e-6
    )
    shifted = camera.obstacle_transmission(grid, (0.0, 0.15))
    np.testing.assert_allclose(shifted, camera.filter.transmission(grid, (0.0, 0.15)), atol=1e-6)
    plain = CameraAperture(stop)
    np.testing.assert_array_equal(plain.obstacle_transmission(grid, (1.0, 2.0)), 1.0)


# ------------------------------------------------------------------------------ gradients


def _psf_loss(build_camera):
    """A scalar of the PSF of `build_camera(x)`, weighted so it is not just the energy."""
    prop = make_propagator(
        window_mm=6.4,
        focal_length_mm=50.0,
        fft_wavelength_nm=LAMBDA_NM,
        shortest_wavelength_nm=LAMBDA_NM,
        npix=48,
        aperture_npix=48,
    )
    weight = jnp.asarray(np.random.default_rng(0).uniform(0.5, 1.5, (48, 48)))

    def loss(x):
        camera = build_camera(x)
        return jnp.sum(prop(camera.transmission(prop.grid), LAMBDA_NM) * weight)

    return jax.jit(loss)


GRADIENT_CASES = {
    "rotation_deg": (lambda x: CameraAperture(Diaphragm(6, 8.0, 40.0, rotation_deg=x)), 10.0),
    "rounding": (lambda x: CameraAperture(Diaphragm(6, 8.0, 40.0, rounding=x)), 0.3),
    "f_number": (lambda x: CameraAperture(Diaphragm(5, x, 40.0, rounding=0.2)), 8.0),
    "spacing_mm": (
        lambda x: CameraAperture(Diaphragm(6, 8.0, 40.0), filter=CrossScreen((0.0, 60.0), x, 0.2)),
        0.37,
    ),
    "duty_cycle": (
        lambda x: CameraAperture(Diaphragm(6, 8.0, 40.0), filter=CrossScreen((20.0,), 0.4, x)),
        0.25,
    ),
    "cross_screen_angle": (
        lambda x: CameraAperture(Diaphragm(6, 8.0, 40.0), filter=CrossScreen((x,), 0.4, 0.25)),
        20.0,
    ),
    "dust_density": (
        lambda x: CameraAperture(Diaphragm(6, 8.0, 40.0), dust=Dust(x, 0.8, 0.8, key=2)),
        0.3,
    ),
    "dust_opacity": (
        lambda x: CameraAperture(Diaphragm(6, 8.0, 40.0), dust=Dust(0.3, x, 0.8, key=2)),
        0.6,
    ),
    "focal_length_mm": (lambda x: CameraAperture(Diaphragm(7, 8.0, x, rounding=0.1)), 40.0),
    "line_offset_mm": (
        lambda x: CameraAperture(
            Diaphragm(6, 8.0, 40.0), filter=CrossScreen((20.0,), 0.4, 0.25, line_offset_mm=x)
        ),
        0.013,
    ),
    "dust_feature_size_mm": (
        lambda x: CameraAperture(Diaphragm(6, 8.0, 40.0), dust=Dust(0.3, 0.8, x, key=2)),
        0.8,
    ),
}


# Relative steps other than 5e-5: the dust's size curves the PSF's energy (per unit power
# through the aperture) more; at 4e-5 the central difference erred by 1.1e-7 (4.7e-5
# relative), converging fourth-fold per halving, to 7e-9 at 1e-5.
_STEP = {"dust_feature_size_mm": 1.25e-5}


@pytest.mark.parametrize("name", list(GRADIENT_CASES))
def test_gradient_converges_to_finite_differences_float64(name):
    """Every float parameter of the camera: autodiff against central differences at steps
    5e-5 and 2.5e-5 of the parameter's scale, the finer within rtol 1e-5 (+ 1e-10
    absolute: rounding of a loss near 1), and the discrepancy at least halved by the
    halving (`helpers.assert_fd_converges`). Measured at twice these steps: about 4x per
    halving where above rounding (f-number 2.5e-7 -> 6.2e-8, spacing 1.2e-6 -> 2.9e-7)."""
    build, x0 = GRADIENT_CASES[name]
    with x64():
        ad, *_ = assert_grad_converges(
            _psf_loss(build), x0, eps=_STEP.get(name, 5e-5) * max(abs(x0), 0.1), rtol=1e-5,
            atol=1e-10,
        )  # fmt: skip
    assert abs(ad) > 1e-6  # the parameter actually moves the PSF


# Which case differentiates each float leaf of a camera with every component.
_CASE_OF_LEAF = {
    "diaphragm.f_number": "f_number",
    "diaphragm.focal_length_mm": "focal_length_mm",
    "diaphragm.rotation_deg": "rotation_deg",
    "diaphragm.rounding": "rounding",
    "filter.angles_deg": "cross_screen_angle",
    "filter.spacing_mm": "spacing_mm",
    "filter.duty_cycle": "duty_cycle",
    "filter.line_offset_mm": "line_offset_mm",
    "dust.density": "dust_density",
    "dust.opacity": "dust_opacity",
    "dust.feature_size_mm": "dust_feature_size_mm",
}


def test_every_float_leaf_has_a_gradient_case():
    params = eqx.filter(_full_camera(), eqx.is_inexact_array)
    paths = {
        jax.tree_util.keystr(path).lstrip(".")
        for path, _ in jax.tree_util.tree_flatten_with_path(params)[0]
    }
    assert paths == set(_CASE_OF_LEAF)
    assert set(_CASE_OF_LEAF.values()) == set(GRADIENT_CASES)


# ------------------------------------------------------------------------------ transformations


@pytest.mark.slow
def test_jit_equals_eager_and_vmap_equals_loop():
    camera = CameraAperture(
        Diaphragm(7, 5.6, 35.0, rotation_deg=3.0, rounding=0.2),
        filter=CrossScreen((0.0, 60.0, 120.0), 0.3, 0.15),
        dust=Dust(0.1, 0.5, 0.6, key=5),
    )
    grid = ApertureGrid.from_width(64, 1.05 * camera.extent_mm())
    eager = camera.transmission(grid)
    jitted = eqx.filter_jit(lambda c: c.transmission(grid))(camera)
    np.testing.assert_allclose(jitted, eager, atol=2e-5)

    f_numbers = jnp.array([4.0, 5.6, 8.0])

    def pupil(n):
        return eqx.tree_at(lambda c: c.diaphragm.f_number, camera, n).pupil_transmission(grid)

    batched = jax.vmap(pupil)(f_numbers)
    one = jax.jit(pupil)
    for i, n in enumerate(f_numbers):
        np.testing.assert_allclose(batched[i], one(n), atol=2e-5)

    shifts = jnp.array([[0.0, 0.0], [0.05, -0.1], [0.3, 0.2]])
    obstacle = jax.jit(lambda s: camera.obstacle_transmission(grid, s))
    moved = jax.vmap(obstacle)(shifts)
    for i, s in enumerate(shifts):
        np.testing.assert_allclose(moved[i], obstacle(s), atol=2e-5)


# ------------------------------------------------------------------------------ bad input


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: Diaphragm(0, 8.0, 50.0), "n_blades must be >= 3.*got 0"),
        (lambda: Diaphragm(2, 8.0, 50.0), "n_blades must be >= 3.*got 2"),
        (lambda: Diaphragm(6.0, 8.0, 50.0), "n_blades must be an integer"),
        (lambda: Diaphragm(6, 0.0, 50.0), "f_number must be finite and > 0, got 0"),
        (lambda: Diaphragm(6, -2.8, 50.0), "f_number.*got -2.8"),
        (lambda: Diaphragm(6, 2.8, -50.0), "focal_length_mm.*got -50"),
        (
            lambda: Diaphragm(6, 2.8, 50.0, rounding=1.5),
            "rounding must be finite, >= 0 and <= 1, got 1.5",
        ),
        (lambda: CrossScreen((0.0,), 0.2, 0.0), "duty_cycle must be finite, > 0 and < 1, got 0"),
        (lambda: CrossScreen((0.0,), 0.2, 1.0), "duty_cycle must be finite, > 0 and < 1, got 1"),
        (lambda: CrossScreen((0.0,), -0.2, 0.5), "spacing_mm must be finite and > 0, got -0.2"),
        (lambda: CrossScreen((), 0.2, 0.5), "one or more angles"),
        (lambda: Dust(1.5, 0.5, 0.3), "density must be finite, >= 0 and <= 1, got 1.5"),
        (lambda: Dust(0.5, -0.1, 0.3), "opacity must be finite, >= 0 and <= 1, got -0.1"),
        (lambda: Dust(0.5, 0.5, 0.0), "feature_size_mm.*got 0"),
    ],
)
def test_bad_values_raise_documented_errors(make, message):
    with pytest.raises(PhysicsRangeError, match=message):
        make()


# ------------------------------------------------------------------------------ configs


def _full_camera():
    return CameraAperture(
        Diaphragm(7, 5.6, 35.0, rotation_deg=12.0, rounding=0.25),
        filter=CrossScreen((0.0, 60.0, 120.0), 0.3, 0.15, line_offset_mm=0.02),
        dust=Dust(0.1, 0.5, 0.6, key=9, octaves=2),
    )


def test_config_round_trip():
    camera = _full_camera()
    table = camera_to_config(camera)
    assert table["seed"] == 9 and table["cross_screen"]["angles_deg"] == [0.0, 60.0, 120.0]
    again = camera_from_config(table)
    assert camera_to_config(again) == table
    grid = ApertureGrid.from_width(48, 1.05 * camera.extent_mm())
    transmission = eqx.filter_jit(lambda c: c.transmission(grid))
    np.testing.assert_array_equal(transmission(again), transmission(camera))
    minimal = camera_from_config(
        {"diaphragm": {"n_blades": 6, "f_number": 2, "focal_length_mm": 50}}
    )
    assert minimal.filter is None and minimal.dust is None
    assert float(minimal.diaphragm.diameter_mm()) == pytest.approx(25.0)


@pytest.mark.parametrize(
    ("table", "error", "message"),
    [
        ({"diaphragm": {}, "lens": 1}, ConfigError, "unknown key 'lens'; valid keys: diaphragm"),
        (
            {"diaphragm": {"n_blades": 6, "f_number": 2, "focal_length_mm": 50, "blades": 3}},
            ConfigError,
            r"\[camera.diaphragm\] has unknown key 'blades'; valid keys: n_blades, f_number",
        ),
        ({"cross_screen": {}}, ConfigError, "needs the key 'diaphragm'"),
        (
            {"diaphragm": {"n_blades": 6, "f_number": "2", "focal_length_mm": 50}},
            ConfigError,
            "camera.diaphragm.f_number must be a number",
        ),
        (
            {"diaphragm": {"n_blades": 6, "f_number": 2, "focal_length_mm": 50}, "seed": 1.5},
            ConfigError,
            "seed must be an integer",
        ),
        (
            {"diaphragm": {"n_blades": 0, "f_number": 2, "focal_length_mm": 50}},
            PhysicsRangeError,
            "camera: diaphragm n_blades must be >= 3",
        ),
        (
            {
                "diaphragm": {"n_blades": 6, "f_number": 2, "focal_length_mm": 50},
                "cross_screen": {"angles_deg": 0.0, "spacing_mm": 0.2, "duty_cycle": 0.1},
            },
            ConfigError,
            "angles_deg must be a non-empty list of numbers",
        ),
    ],
)
def test_bad_config_names_the_key(table, error, message):
    with pytest.raises(error, match=message):
        camera_from_config(table)


def test_dust_from_a_key_cannot_be_written():
    camera = CameraAperture(Diaphragm(6, 2.0, 50.0), dust=Dust(0.1, 0.5, 0.5, jax.random.key(1)))
    with pytest.raises(ConfigError, match="no seed"):
        camera_to_config(camera)
