"""Reference PSFs: the CIE glare function, closed forms against the propagators, profiles.

The closed-form checks compare two independent paths: a closed form from
`invglare.reference` against the foundation's numerical propagation
(`fraunhofer_mft`, `angular_spectrum`) of an aperture rasterised here, in the test,
by supersampled point-in-shape coverage (so neither `invglare.aperture` nor the
reference code is involved in building it).
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import OpenEXR
import pytest
from helpers import assert_grad_matches_fd, x64
from scipy.special import j0 as scipy_j0
from scipy.special import j1 as scipy_j1

from invglare._core.grids import AngularGrid, ApertureGrid
from invglare.errors import ConfigError, InputDataError, PhysicsRangeError
from invglare.files.exr import write_exr
from invglare.optics.fraunhofer import fraunhofer_mft, transmitted_power
from invglare.optics.fresnel import angular_spectrum
from invglare.reference import (
    RadialTable,
    ReferenceImage,
    airy_encircled_energy,
    airy_pixel_psf,
    airy_psf,
    bessel_j1,
    cie_gsf,
    encircled_energy,
    fresnel_square_intensity,
    gsf_to_psf,
    load_reference_psf,
    polygon_area_mm2,
    polygon_far_field,
    psf_to_gsf,
    radial_profile,
    rect_psf,
    regular_polygon_vertices,
    spencer_1995_psf,
    stiles_holladay,
)

DEG = math.pi / 180.0
CIE_ANGLES = [0.1, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0]


def cie_by_hand(theta, age, p):
    """The CIE 135/1 general disability glare equation, typed in again from the standard."""
    theta = np.asarray(theta, dtype=np.float64)
    age_term = (age / 70.0) ** 4
    lens = 9.2e6 / (1 + (theta / 0.0046) ** 2) ** 1.5 + 1.5e5 / (1 + (theta / 0.045) ** 2) ** 1.5
    x = 1 + (theta / 0.1) ** 2
    rest = (400 / x + 3e-8 * theta**2) + p * (1300 / x**1.5 + 0.8 / x**0.5)
    return (1 - 0.08 * age_term) * lens + (1 + 1.6 * age_term) * rest + 2.5e-3 * p


def supersampled(inside, n: int, pitch: float, ss: int = 16) -> np.ndarray:
    """Coverage of each pixel of an n x n grid (centre pixel n // 2) by ss x ss point tests."""
    c = (np.arange(n) - n // 2) * pitch
    offsets = ((np.arange(ss) + 0.5) / ss - 0.5) * pitch
    acc = np.zeros((n, n))
    for oy in offsets:
        for ox in offsets:
            acc += inside(c[None, :] + ox, c[:, None] + oy)
    return acc / ss**2


# ------------------------------------------------------------------ CIE glare spread function


@pytest.mark.parametrize(("age", "p"), [(25.0, 0.5), (70.0, 1.0)])
def test_cie_values_at_tabulated_angles_match_independent_formula(age, p):
    expected = cie_by_hand(CIE_ANGLES, age, p)
    with x64():
        got = np.asarray(cie_gsf(jnp.asarray(CIE_ANGLES), age, p))
    np.testing.assert_allclose(got, expected, rtol=1e-12)
    # float32 default: same values to float32 precision.
    np.testing.assert_allclose(np.asarray(cie_gsf(CIE_ANGLES, age, p)), expected, rtol=2e-6)


def test_cie_hand_checked_numbers():
    # Worked by hand from the equation (A = 25, p = 0.5): the terms at 1 deg are
    # 0.895 + 13.62 (optics), 3.96 (scatter), 0.5 * (1.281 + 0.0796) (pigment).
    with x64():
        assert float(cie_gsf(1.0, 25.0, 0.5)) == pytest.approx(19.2665, rel=1e-4)
        assert float(cie_gsf(10.0, 25.0, 0.5)) == pytest.approx(0.061606, rel=1e-4)


def test_cie_integrates_to_about_one_over_the_plane():
    # A GSF is a PSF: the light it spreads over the plane (solid angle in sr) is ~1.
    with x64():
        theta = jnp.concatenate([jnp.linspace(0.0, 0.1, 4001), jnp.geomspace(0.1, 100.0, 40001)])
        f = cie_gsf(theta, 0.0, 0.0, extrapolate=True) * 2 * math.pi * theta * DEG**2
        total = float(jnp.trapezoid(f, theta))
    assert 0.95 < total < 1.05


@pytest.mark.parametrize(("age", "p"), [(0.0, 0.0), (25.0, 0.5), (70.0, 1.0), (100.0, 1.2)])
def test_cie_decreases_with_angle(age, p):
    with x64():
        v = np.asarray(cie_gsf(jnp.geomspace(0.1, 100.0, 3000), age, p))
    assert np.all(np.diff(v) < 0)


def test_cie_rises_with_age_beyond_0_3_deg_and_with_pigmentation_everywhere():
    theta = jnp.geomspace(0.3, 100.0, 200)
    ages = [20.0, 40.0, 60.0, 80.0]
    by_age = np.stack([np.asarray(cie_gsf(theta, a, 0.5)) for a in ages])
    assert np.all(np.diff(by_age, axis=0) > 0)
    theta_all = jnp.geomspace(0.1, 100.0, 200)
    by_p = np.stack([np.asarray(cie_gsf(theta_all, 50.0, p)) for p in (0.0, 0.5, 1.0, 1.2)])
    assert np.all(np.diff(by_p, axis=0) > 0)
    # Pigmentation matters far out (light through the eye wall), barely near the core.
    ratio = by_p[2] / by_p[0]
    assert ratio[-1] > 2.0 and ratio[0] < 1.1


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"theta_deg": 0.05}, "0.05 deg is outside the validity range 0.1-100"),
        ({"theta_deg": 150.0}, "150 deg"),
        ({"theta_deg": [1.0, np.nan]}, "finite"),
        ({"theta_deg": 1.0, "age": 150.0}, "age = 150 years"),
        ({"theta_deg": 1.0, "age": -1.0}, "age = -1"),
        ({"theta_deg": 1.0, "pigmentation": 1.5}, "pigmentation = 1.5"),
        ({"theta_deg": 1.0, "pigmentation": -0.1}, "pigmentation = -0.1"),
    ],
)
def test_cie_range_errors_name_the_value(kwargs, match):
    with pytest.raises(PhysicsRangeError, match=match):
        cie_gsf(**kwargs)


def test_cie_extrapolate_flag():
    theta = [0.0, 0.01, 150.0]
    with x64():
        got = np.asarray(cie_gsf(jnp.asarray(theta), 25.0, 0.5, extrapolate=True))
    np.testing.assert_allclose(got, cie_by_hand(theta, 25.0, 0.5), rtol=1e-12)
    # The age check is not lifted by extrapolate.
    with pytest.raises(PhysicsRangeError, match="age = 101"):
        cie_gsf(1.0, 101.0, extrapolate=True)


def test_cie_jit_and_vmap():
    theta = jnp.asarray(CIE_ANGLES)
    eager = cie_gsf(theta, 50.0, 0.7)
    np.testing.assert_allclose(jax.jit(cie_gsf)(theta, 50.0, 0.7), eager, rtol=1e-6)
    ages = jnp.array([20.0, 45.0, 80.0])
    mapped = jax.vmap(lambda a: cie_gsf(theta, a, 0.5))(ages)
    loop = jnp.stack([cie_gsf(theta, float(a), 0.5) for a in ages])
    np.testing.assert_allclose(mapped, loop, rtol=1e-6)


def test_cie_gradients_match_finite_differences_float64():
    with x64():
        assert_grad_matches_fd(lambda a: cie_gsf(3.0, a, 0.5), 50.0, eps=1e-4, rtol=1e-7)
        assert_grad_matches_fd(lambda a: cie_gsf(0.2, a, 1.0), 70.0, eps=1e-4, rtol=1e-7)
        assert_grad_matches_fd(lambda p: cie_gsf(30.0, 40.0, p), 0.5, eps=1e-6, rtol=1e-7)
        assert_grad_matches_fd(lambda t: cie_gsf(t, 40.0, 0.5), 2.0, eps=1e-6, rtol=1e-7)


# ------------------------------------------------------------------ Stiles-Holladay, Spencer


def test_stiles_holladay_and_age_adjusted_form():
    theta = np.array([1.0, 2.0, 5.0, 10.0, 30.0])
    with x64():
        np.testing.assert_allclose(stiles_holladay(theta), 10.0 / theta**2, rtol=1e-15)
        np.testing.assert_allclose(stiles_holladay(theta, 62.5), 20.0 / theta**2, rtol=1e-15)
        np.testing.assert_allclose(stiles_holladay(theta, 0.0), 10.0 / theta**2, rtol=1e-15)
        np.testing.assert_allclose(
            stiles_holladay(theta, 31.25), (1 + 1 / 16) * 10.0 / theta**2, rtol=1e-15
        )
    with pytest.raises(PhysicsRangeError, match=r"0\.5 deg is outside the validity range 1-30"):
        stiles_holladay(0.5)
    with pytest.raises(PhysicsRangeError, match="age = 150"):
        stiles_holladay(5.0, 150.0)
    assert float(stiles_holladay(0.5, extrapolate=True)) == pytest.approx(40.0)


def test_spencer_values_and_normalisation():
    theta = np.array([0.0, 0.01, 0.1, 1.0, 10.0])
    f0 = 2.61e6 * np.exp(-((theta / 0.02) ** 2))
    f1 = 20.91 / (theta + 0.02) ** 3
    f2 = 72.37 / (theta + 0.02) ** 2
    with x64():
        np.testing.assert_allclose(
            spencer_1995_psf(theta), 0.384 * f0 + 0.478 * f1 + 0.138 * f2, rtol=1e-13
        )
        # The core and the near wings are each unit-energy PSFs in sr^-1 (theta in deg):
        # this is what fixes the units, whatever one recalls of the paper.
        t = jnp.concatenate([jnp.linspace(0.0, 1.0, 200001), jnp.geomspace(1.0, 1e5, 20001)[1:]])
        for weights in ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)):
            f = spencer_1995_psf(t, weights) * 2 * math.pi * t * DEG**2
            assert float(jnp.trapezoid(f, t)) == pytest.approx(1.0, abs=2e-3)
    assert sum((0.384, 0.478, 0.138)) == pytest.approx(1.0)


# ------------------------------------------------------------------ closed forms


def test_bessel_j1_and_airy_encircled_energy_against_scipy():
    with x64():
        x = np.concatenate([np.linspace(0.0, 40.0, 4001), np.linspace(40.0, 3000.0, 3001)])
        np.testing.assert_allclose(bessel_j1(x), scipy_j1(x), rtol=0, atol=1e-13)
        v = np.linspace(0.0, 60.0, 601)
        lam_mm, d = 550e-6, 4.0
        theta = v * lam_mm / (math.pi * d)
        expected = 1 - scipy_j0(v) ** 2 - scipy_j1(v) ** 2
        np.testing.assert_allclose(airy_encircled_energy(theta, d, 550.0), expected, atol=1e-12)
        # Airy peak: pi D^2 / (4 lambda^2), the pupil area over lambda^2.
        peak = math.pi * d**2 / (4 * lam_mm**2)
        assert float(airy_psf(0.0, d, 550.0)) == pytest.approx(peak, rel=1e-14)


def test_airy_pixel_psf_matches_mft_of_rasterised_disk():
    """Disk 128 px across, 16x16 supersampled coverage, MFT on a 128 px grid of lambda / 4D.

    Measured: 5.4e-5 of the peak once the raster's power is matched (below); 5.4e-3
    raw. The raw gap is real physics of a grey-level raster, not error: an edge pixel
    of coverage c passes amplitude c but power c² < c, so `fraunhofer_mft` (which
    divides by the raster's power) has a peak higher by area / sum(c² pitch²).
    """
    with x64():
        d, lam, n = 4.0, 550.0, 144
        pitch = d / 128
        disk = supersampled(lambda x, y: x * x + y * y <= (d / 2) ** 2, n, pitch)
        out = AngularGrid(128, lam * 1e-6 / (4 * d) / DEG)
        mft = np.asarray(fraunhofer_mft(jnp.asarray(disk), ApertureGrid(n, pitch), lam, out))
        ref = np.asarray(airy_pixel_psf(out, d, lam))
        power = float(transmitted_power(jnp.asarray(disk), pitch))
        area = math.pi * d**2 / 4
    peak = ref.max()
    assert np.abs(mft * power / area - ref).max() < 2e-4 * peak
    assert np.abs(mft - ref).max() < 1e-2 * peak


def test_polygon_far_field_matches_mft_of_rasterised_hexagon():
    """Hexagon (4 mm across corners, rotated 10 deg), same sampling as the disk test.

    Measured: 3.3e-5 of the peak with the raster's power matched, 6.0e-3 raw (grey
    edge pixels, as for the disk); tolerances 2e-4 and 1e-2 of the peak.
    """
    with x64():
        d, lam, n = 4.0, 550.0, 144
        pitch = d / 128
        hexagon = regular_polygon_vertices(6, d, 10.0)
        v = np.asarray(hexagon)

        def inside(x, y):
            ok = np.ones(np.broadcast(x, y).shape, dtype=bool)
            for i in range(6):
                a, b = v[i], v[(i + 1) % 6]
                ok &= (b[0] - a[0]) * (y - a[1]) - (b[1] - a[1]) * (x - a[0]) >= 0
            return ok

        raster = supersampled(inside, n, pitch)
        out = AngularGrid(128, lam * 1e-6 / (4 * d) / DEG)
        mft = np.asarray(fraunhofer_mft(jnp.asarray(raster), ApertureGrid(n, pitch), lam, out))
        c = out.coords_rad()
        ref = polygon_far_field(c[None, :], c[:, None], hexagon, lam) * out.solid_angle_sr()
        ref = np.asarray(ref)
        power = float(transmitted_power(jnp.asarray(raster), pitch))
        area = float(polygon_area_mm2(hexagon))
    assert area == pytest.approx(1.5 * math.sqrt(3) * (d / 2) ** 2, rel=1e-14)
    peak = ref.max()
    assert np.abs(mft * power / area - ref).max() < 2e-4 * peak
    assert np.abs(mft - ref).max() < 1e-2 * peak


def test_rect_psf_matches_mft_of_pixel_aligned_rectangle():
    """A 64 x 32 px rectangle of whole pixels. Measured 3.3e-4 of the peak: the DFT of
    samples is a Dirichlet kernel, sinc times (pi f d) / sin(pi f d)."""
    with x64():
        n, pitch, lam = 144, 4.0 / 128, 550.0
        raster = np.zeros((n, n))
        raster[n // 2 - 16 : n // 2 + 16, n // 2 - 32 : n // 2 + 32] = 1.0
        out = AngularGrid(128, lam * 1e-6 / 16.0 / DEG)
        mft = np.asarray(fraunhofer_mft(jnp.asarray(raster), ApertureGrid(n, pitch), lam, out))
        c = out.coords_rad()
        ref = rect_psf(c[None, :], c[:, None], 64 * pitch, 32 * pitch, lam)
        ref = np.asarray(ref * out.solid_angle_sr())
    assert np.abs(mft - ref).max() < 1e-3 * ref.max()


def test_polygon_equals_rect_including_singular_directions():
    # Axes (f perpendicular to two edges) and the origin (f = 0) included; the grid also
    # straddles the switch to the Taylor branch near f = 0.
    rect = np.array([[-1.0, -0.5], [1.0, -0.5], [1.0, 0.5], [-1.0, 0.5]])
    theta = np.concatenate([np.linspace(-2e-3, 2e-3, 201), np.geomspace(1e-9, 1e-4, 50)])
    tx, ty = np.meshgrid(theta, 0.7 * theta)
    with x64():
        got = np.asarray(polygon_far_field(tx, ty, rect, 500.0))
        ref = np.asarray(rect_psf(tx, ty, 2.0, 1.0, 500.0))
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12 * ref.max())
        # Reversed (clockwise) vertices give the same intensity.
        rev = np.asarray(polygon_far_field(tx, ty, rect[::-1], 500.0))
        np.testing.assert_allclose(rev, ref, rtol=0, atol=1e-12 * ref.max())
        # Gradients are finite at f = 0 and match finite differences elsewhere.
        g0 = jax.grad(lambda t: polygon_far_field(t, 0.3 * t, rect, 500.0))(0.0)
        assert np.isfinite(float(g0))
        assert_grad_matches_fd(
            lambda t: polygon_far_field(t, 0.3 * t, rect, 500.0), 1e-4, eps=1e-9, rtol=1e-6
        )
    got32 = polygon_far_field(tx.astype(np.float32), ty.astype(np.float32), rect, 500.0)
    np.testing.assert_allclose(got32, ref, rtol=0, atol=1e-5 * ref.max())


def test_airy_energy_on_grid_is_the_encircled_energy():
    """Point-sampled Airy on 256 px of lambda / 8D: measured |diff| < 4e-5 from ring 1 out."""
    with x64():
        d, lam = 4.0, 550.0
        out = AngularGrid(256, lam * 1e-6 / (8 * d) / DEG)
        psf = airy_pixel_psf(out, d, lam)
        radii_rad = np.array([1.22, 2.23, 3.24, 5.0, 10.0, 15.0]) * lam * 1e-6 / d
        ee = np.asarray(encircled_energy(psf, out.pixel_scale_deg, radii_rad / DEG, total=1.0))
        v = math.pi * d * radii_rad / (lam * 1e-6)
        np.testing.assert_allclose(ee, 1 - scipy_j0(v) ** 2 - scipy_j1(v) ** 2, atol=1e-4)
        # Pixel-integrated (3x3) holds the same energy.
        psf3 = airy_pixel_psf(out, d, lam, oversample=3)
        assert float(psf3.sum()) == pytest.approx(float(psf.sum()), abs=1e-4)


def test_airy_jit_vmap_and_gradient():
    theta = jnp.linspace(0.0, 1e-3, 64)
    lams = jnp.array([450.0, 550.0, 650.0])
    mapped = jax.vmap(lambda lam: airy_psf(theta, 4.0, lam))(lams)
    loop = jnp.stack([airy_psf(theta, 4.0, float(lam)) for lam in lams])
    np.testing.assert_allclose(mapped, loop, rtol=1e-5)
    grid = AngularGrid(32, 0.002)
    jitted = jax.jit(airy_pixel_psf)(grid, 4.0, 550.0)
    eager = airy_pixel_psf(grid, 4.0, 550.0)
    # float32: compare against the peak (the values near the dark rings are round-off).
    np.testing.assert_allclose(jitted, eager, rtol=0, atol=1e-5 * float(eager.max()))
    with x64():
        assert_grad_matches_fd(lambda d: airy_psf(2e-4, d, 550.0), 4.0, eps=1e-6, rtol=1e-6)


def test_fresnel_square_matches_angular_spectrum_and_its_limits():
    """Side 1 mm, 500 nm, z = 200 mm (Fresnel number 10), 512 px of 1/128 mm padded to 1024.

    Measured max |diff| 5.1e-3 with a peak of 2.2 (the edge discontinuity is sampled
    by the raster); tolerance 1e-2 of the peak over the central 2 x 2 mm.
    """
    side, lam, z, n = 1.0, 500.0, 200.0, 512
    pitch = 4.0 / n
    k = round(0.5 * side / pitch)
    square = np.zeros((n, n))
    square[n // 2 - k : n // 2 + k, n // 2 - k : n // 2 + k] = 1.0
    with x64():
        field = angular_spectrum(
            jnp.asarray(square, dtype=jnp.complex128),
            ApertureGrid(n, pitch),
            lam,
            z,
            pad_npix=2 * n,
            kind="fresnel",
        )
        numeric = np.abs(np.asarray(field)) ** 2
    # The whole-pixel square spans pixels n//2 - k .. n//2 + k - 1: its centre is half a
    # pixel below the grid origin.
    x = (np.arange(n) - n // 2) * pitch + 0.5 * pitch
    exact = fresnel_square_intensity(x[None, :], x[:, None], side, lam, z)
    window = np.abs(x) < 1.0
    diff = np.abs(numeric - exact)[np.ix_(window, window)]
    assert diff.max() < 1e-2 * exact.max()
    # Far field (Fresnel number 0.01): the Fraunhofer pattern of rect_psf.
    z_far = 2e5
    xs = np.linspace(-200.0, 200.0, 41)
    far = fresnel_square_intensity(xs, 0.3 * xs, side, lam, z_far)
    fraunhofer = np.asarray(rect_psf(xs / z_far, 0.3 * xs / z_far, side, side, lam))
    np.testing.assert_allclose(far, fraunhofer * side**2 / z_far**2, rtol=0, atol=2e-2 * far.max())
    # Near field (Fresnel number 1e4): geometric shadow, 1 well inside the square.
    assert fresnel_square_intensity(0.0, 0.0, side, lam, 0.2) == pytest.approx(1.0, abs=0.05)
    assert fresnel_square_intensity(1.0, 0.0, side, lam, 0.2) < 1e-3


# ------------------------------------------------------------------ profiles


def test_radial_profile_of_analytic_images():
    n, scale = 101, 0.02
    c = (np.arange(n) - n // 2) * scale
    r = np.hypot(c[None, :], c[:, None])
    linear = 3.0 + 2.0 * r
    theta, prof = radial_profile(jnp.asarray(np.stack([linear, 2 * linear])), scale)
    theta = np.asarray(theta)
    assert theta.shape == (50,) and prof.shape == (2, 50)
    # Linear in r: exact at the returned mean pixel distance.
    np.testing.assert_allclose(prof[0], 3.0 + 2.0 * theta, rtol=1e-5)
    np.testing.assert_allclose(prof[1], 2 * prof[0], rtol=1e-6)
    # A Gaussian (sigma 10 px), 1 px annuli: second-order bias below 1e-3 of the peak.
    sigma = 10 * scale
    gauss = np.exp(-(r**2) / (2 * sigma**2))
    theta, prof = radial_profile(jnp.asarray(gauss), scale, n_bins=50, max_angle_deg=1.0)
    np.testing.assert_allclose(prof, np.exp(-(np.asarray(theta) ** 2) / (2 * sigma**2)), atol=1e-3)
    # Under jit with a static bin count.
    jitted = jax.jit(radial_profile, static_argnums=(2,))(jnp.asarray(gauss), scale, 50, 1.0)
    np.testing.assert_allclose(jitted[1], prof, rtol=1e-6)


def test_encircled_energy_of_delta_and_uniform_disk():
    n = 81
    delta = np.zeros((n, n))
    delta[n // 2, n // 2] = 1.0
    ee = np.asarray(encircled_energy(jnp.asarray(delta), 1.0, jnp.array([0.25, 0.5, 0.8, 3.0])))
    np.testing.assert_allclose(ee, [math.pi / 16, math.pi / 4, 1.0, 1.0], atol=1e-6)
    # A uniform disk of radius 30 px: EE(R) = (R / 30)^2 inside it, 1 outside.
    disk = supersampled(lambda x, y: x * x + y * y <= 30.0**2, n, 1.0)
    radii = np.array([3.0, 5.0, 10.0, 20.0, 28.0, 32.0, 38.0])
    ee = np.asarray(encircled_energy(jnp.asarray(disk), 0.1, jnp.asarray(radii * 0.1)))
    np.testing.assert_allclose(ee, np.minimum(radii / 30.0, 1.0) ** 2, atol=1e-3)


def test_cie_round_trip_through_gsf_to_psf_and_psf_to_gsf():
    """0.01 deg pixels, +-2 deg: measured 0.5 % worst (at 0.1 deg, 10 px out)."""
    with x64():
        for age, p in ((25.0, 0.5), (70.0, 1.0)):
            grid = AngularGrid(401, 0.01)
            psf = gsf_to_psf(lambda t, a=age, q=p: cie_gsf(t, a, q, extrapolate=True), grid)
            theta, gsf = psf_to_gsf(psf, 0.01)
            theta, gsf = np.asarray(theta), np.asarray(gsf)
            keep = (theta >= 0.1) & (theta <= 2.0)
            expected = np.asarray(cie_gsf(theta[keep], age, p))
            np.testing.assert_allclose(gsf[keep], expected, rtol=0.02)
            # The grid holds ~98 % of the light within 2 deg; "unit" rescales to 1.
            assert 0.95 < float(psf.sum()) < 1.0
            unit = gsf_to_psf(lambda t: cie_gsf(t, extrapolate=True), grid, "unit")
            assert float(unit.sum()) == pytest.approx(1.0, rel=1e-12)


def test_gsf_to_psf_with_a_table_and_its_errors():
    theta = np.geomspace(0.5, 50.0, 60)
    table = RadialTable(theta, 10.0 / theta**2)
    assert table.log_log
    probe = jnp.array([0.7, 3.3, 21.0])
    np.testing.assert_allclose(table(probe), 10.0 / np.asarray(probe) ** 2, rtol=1e-5)
    assert float(table(0.1)) == pytest.approx(10.0 / 0.25, rel=1e-5)  # held below the table
    assert float(table(60.0)) == 0.0  # nothing claimed beyond it
    grid = AngularGrid(64, 0.5)
    from_pair = gsf_to_psf((theta, 10.0 / theta**2), grid)
    np.testing.assert_allclose(from_pair, gsf_to_psf(table, grid), rtol=1e-6)
    with pytest.raises(ConfigError, match="normalise = 'peak'"):
        gsf_to_psf(table, grid, "peak")
    # A function that refuses part of the grid: the error says how to extrapolate.
    with pytest.raises(PhysicsRangeError, match="extrapolate=True"):
        gsf_to_psf(lambda t: cie_gsf(t), grid)


@pytest.mark.parametrize(
    ("theta", "values", "match"),
    [
        ([0.1, 0.3, 0.2, 1.0], [4.0, 3.0, 2.0, 1.0], "not strictly increasing at index 2"),
        ([0.1, 0.3, 0.3, 1.0], [4.0, 3.0, 2.0, 1.0], "at index 2"),
        ([0.1, 0.3, 1.0], [4.0, np.nan, 1.0], r"value\[1\] \(at 0.3 deg\) is nan"),
        ([0.1, 0.3, 1.0], [4.0, -2.0, 1.0], r"value\[1\] \(at 0.3 deg\) is -2"),
        ([-0.1, 0.3, 1.0], [4.0, 2.0, 1.0], "negative"),
        ([0.1, 0.3], [4.0, 2.0, 1.0], "2 entries but values has 3"),
    ],
)
def test_radial_table_validation(theta, values, match):
    with pytest.raises(InputDataError, match=match):
        RadialTable(theta, values, source="my-table")


def test_load_reference_psf_tables_and_exr(tmp_path):
    good = tmp_path / "cie.csv"
    good.write_text("# CIE, age 25\ntheta_deg,value\n0.1,11685\n1,19.27\n10,0.0616\n")
    table = load_reference_psf(good)
    assert isinstance(table, RadialTable)
    np.testing.assert_allclose(table.theta_deg, [0.1, 1.0, 10.0])
    spaced = tmp_path / "cie.txt"
    spaced.write_text("0.1 11685\n1 19.27\n10 0.0616\n")
    np.testing.assert_allclose(load_reference_psf(spaced).values, table.values)

    bad = tmp_path / "bad.csv"
    bad.write_text("0.1,5\n1,4\n0.5,3\n")
    with pytest.raises(InputDataError, match=r"bad\.csv.*not strictly increasing at index 2"):
        load_reference_psf(bad)
    nan = tmp_path / "nan.csv"
    nan.write_text("0.1,5\n1,nan\n")
    with pytest.raises(InputDataError, match=r"nan\.csv.*value\[1\]"):
        load_reference_psf(nan)
    three = tmp_path / "three.csv"
    three.write_text("0.1,5,6\n")
    with pytest.raises(InputDataError, match="line 1 has 3 column"):
        load_reference_psf(three)
    with pytest.raises(InputDataError, match="not found"):
        load_reference_psf(tmp_path / "missing.csv")
    with pytest.raises(InputDataError, match=r"unknown reference PSF format '\.png'"):
        load_reference_psf(tmp_path / "psf.png")

    psf = np.asarray(airy_pixel_psf(AngularGrid(33, 0.01), 2.0, 550.0), dtype=np.float32)
    with_scale = write_exr(tmp_path / "ref.exr", psf, pixel_scale_deg=0.01)
    image = load_reference_psf(with_scale)
    assert isinstance(image, ReferenceImage)
    assert image.pixel_scale_deg == 0.01
    np.testing.assert_array_equal(image.psf, psf)

    # write_exr always stores the pixel scale, so write a bare file with OpenEXR itself.
    bare = tmp_path / "bare.exr"
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"Y": psf}) as exr:
        exr.write(str(bare))
    with pytest.raises(InputDataError, match=r"bare\.exr.*no pixelScaleDeg"):
        load_reference_psf(bare)
