"""Tests of `invglare.optics.spectral`: wavelengths, XYZ weights, RGB, and scaled-copy PSFs.

Closed forms: the Airy pattern ``[2 J1(x) / x]^2`` with ``x = pi r / p`` (``p`` pixels per
lambda / D), whose Fraunhofer scaling with wavelength is exact, so resampling errors are
those of bilinear interpolation alone. Colorimetry is checked against colour-science's own
integration.
"""

from __future__ import annotations

import colour
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import assert_grad_matches_fd, x64
from jax.scipy.ndimage import map_coordinates
from scipy.special import j1

from invglare.errors import ConfigError, PhysicsRangeError
from invglare.optics.spectral import (
    parse_wavelengths,
    psf_to_xyz,
    scale_psf,
    scaled_copies_xyz,
    spectral_psf_rgb,
    spectral_weights,
    xyz_to_rgb,
)

CIE1931 = "CIE 1931 2 Degree Standard Observer"
PAPER = "380:770:32"


def airy(npix: int, px_per_fringe: float) -> np.ndarray:
    """Unit-energy Airy pattern (energy per pixel), centre at ``npix // 2``.

    ``px_per_fringe`` is lambda / D in pixels; the plane integral of the peak-1 pattern is
    ``4 p^2 / pi``, hence the normalisation.
    """
    k = np.arange(npix) - npix // 2
    x = np.pi * np.hypot(k[:, None], k[None, :]) / px_per_fringe
    safe = np.where(x == 0, 1.0, x)
    peak1 = np.where(x == 0, 1.0, (2 * j1(safe) / safe) ** 2)
    return peak1 * np.pi / (4 * px_per_fringe**2)


def gaussians(npix: int) -> np.ndarray:
    """Asymmetric smooth unit-energy test pattern, well inside the field (std 5-6 px)."""
    k = np.arange(npix) - npix // 2
    y, x = k[:, None], k[None, :]
    g = np.exp(-(x**2 + y**2) / (2 * 6.0**2)) + 0.5 * np.exp(
        -((x - 9) ** 2 + (y + 5) ** 2) / (2 * 5.0**2)
    )
    return g / g.sum()


# --------------------------------------------------------------------------- parse_wavelengths


def test_parse_range_is_the_papers_sampling():
    wl = parse_wavelengths(PAPER)
    assert wl.shape == (32,)
    assert wl[0] == 380.0
    np.testing.assert_allclose(np.diff(wl), 12.1875, rtol=0, atol=1e-12)
    assert wl[-1] == 757.8125  # stop (770) excluded


@pytest.mark.parametrize(
    ("spec", "expected"),
    [
        (550, [550.0]),
        (550.5, [550.5]),
        ([450, 550, 650], [450.0, 550.0, 650.0]),
        ((450.0, 650.0), [450.0, 650.0]),
        (np.array([500.0, 600.0]), [500.0, 600.0]),
        ("550", [550.0]),
        (" 450, 550 ,650 ", [450.0, 550.0, 650.0]),
        ("400:700:3", [400.0, 500.0, 600.0]),
    ],
)
def test_parse_forms(spec, expected):
    out = parse_wavelengths(spec)
    assert out.dtype == np.float64 and out.ndim == 1
    np.testing.assert_array_equal(out, expected)


@pytest.mark.parametrize(
    "spec", ["abc", "", "380:770", "380:770:0", "770:380:32", "380:770:3.5", "450;550", "550nm"]
)
def test_parse_bad_string_is_config_error(spec):
    with pytest.raises(ConfigError, match="start:stop:n") as info:
        parse_wavelengths(spec)
    assert repr(spec) in str(info.value)


def test_parse_bad_objects_are_config_errors():
    with pytest.raises(ConfigError, match="1-D"):
        parse_wavelengths([[450.0, 550.0]])
    with pytest.raises(ConfigError):
        parse_wavelengths({"a": 1})
    with pytest.raises(ConfigError):
        parse_wavelengths(True)


@pytest.mark.parametrize("spec", [5.5e-7, "5.5e-7", [4.5e-7, 5.5e-7]])
def test_parse_metres_is_physics_range_error(spec):
    with pytest.raises(PhysicsRangeError, match="metres"):
        parse_wavelengths(spec)


def test_parse_micrometres_is_physics_range_error():
    with pytest.raises(PhysicsRangeError, match="micrometres"):
        parse_wavelengths(0.55)


# --------------------------------------------------------------------------- spectral_weights


@pytest.mark.parametrize(
    ("spec", "illuminant"),
    [(PAPER, "E"), (PAPER, "D65"), ("450,550,650", "A"), (np.arange(380.0, 781.0), "D50")],
)
def test_weights_luminance_sums_to_one(spec, illuminant):
    w = spectral_weights(spec, illuminant)
    assert w.shape == (parse_wavelengths(spec).size, 3)
    np.testing.assert_allclose(w[:, 1].sum(), 1.0, rtol=1e-12)
    assert np.all(w >= 0)


def test_single_wavelength_has_unit_luminance_and_its_cmf_ratio():
    w = spectral_weights(550.0)
    bar = colour.MSDS_CMFS[CIE1931][550.0]
    np.testing.assert_allclose(w[0], bar / bar[1], rtol=1e-12)


@pytest.mark.filterwarnings("ignore:Aligning")  # colour trims the flat spectrum to 360-780 nm
def test_equal_energy_matches_colour_integration():
    """1 nm samples over 380-780 nm, illuminant E: X/Y and Z/Y within 1e-3 of colour-science.

    Reference 1: ``colour.sd_to_XYZ`` of a flat spectrum (its own integration, over
    360-780 nm). Reference 2: the plain sums of the CMF table rows at the same
    wavelengths, which uniform bins must reproduce to rounding.
    """
    wl = np.arange(380.0, 781.0, 1.0)
    w = spectral_weights(wl, "E")
    ratios = w.sum(axis=0) / w[:, 1].sum()

    cmfs = colour.MSDS_CMFS[CIE1931]
    flat = colour.SpectralDistribution(dict(zip(cmfs.wavelengths, np.ones(cmfs.wavelengths.size))))
    xyz = colour.sd_to_XYZ(flat, cmfs, colour.SDS_ILLUMINANTS["E"])
    np.testing.assert_allclose(ratios, xyz / xyz[1], atol=1e-3)

    table = cmfs.values[np.isin(cmfs.wavelengths, wl)]
    np.testing.assert_allclose(ratios, table.sum(axis=0) / table[:, 1].sum(), rtol=1e-12)


@pytest.mark.parametrize("spec", [PAPER, np.arange(380.0, 781.0, 1.0)])
def test_d65_weights_have_d65_chromaticity(spec):
    """xy of the summed D65 weights within 2e-3 of (0.3127, 0.3290).

    Measured: (0.31280, 0.32913) with the paper's 32 samples, (0.31274, 0.32905) at 1 nm.
    """
    xyz = spectral_weights(spec, "D65").sum(axis=0)
    xy = xyz[:2] / xyz.sum()
    np.testing.assert_allclose(xy, [0.3127, 0.3290], atol=2e-3)


def test_illuminant_array_and_scale_invariance():
    wl = parse_wavelengths(PAPER)
    d65 = np.asarray(colour.SDS_ILLUMINANTS["D65"][wl])
    np.testing.assert_allclose(spectral_weights(wl, d65), spectral_weights(wl, "D65"), rtol=1e-12)
    np.testing.assert_allclose(
        spectral_weights(wl, np.full(wl.size, 2.5)), spectral_weights(wl, "E"), rtol=1e-12
    )


def test_uneven_sampling_weights_each_sample_by_its_band():
    """1 nm below 500 nm, 10 nm above: X/Y and Z/Y within 5e-3 of uniform 1 nm sampling.

    Measured 1.2e-3 (X) and 2.1e-3 (Z), mostly from the lopsided cell at the 500 nm
    junction; equal weights per sample would be off by tens of percent.
    """
    uneven = np.concatenate([np.arange(380.0, 500.0), np.arange(500.0, 781.0, 10.0)])
    dense = np.arange(380.0, 781.0)
    ratios = [w.sum(axis=0) for w in (spectral_weights(uneven), spectral_weights(dense))]
    np.testing.assert_allclose(ratios[0], ratios[1], atol=5e-3)


def test_weights_do_not_depend_on_sample_order():
    wl = np.array([420.0, 480.0, 500.0, 610.0, 700.0])  # uneven spacing: bins differ
    w = spectral_weights(wl, "D65")
    np.testing.assert_allclose(spectral_weights(wl[::-1], "D65"), w[::-1], rtol=1e-12)


def test_weights_errors():
    with pytest.raises(ConfigError, match="D65") as info:
        spectral_weights(PAPER, "D66")
    assert "'D66'" in str(info.value)
    with pytest.raises(ConfigError, match=CIE1931):
        spectral_weights(PAPER, observer="CIE 1931 3 Degree")
    with pytest.raises(ConfigError, match="XYZ"):  # cone fundamentals are not XYZ CMFs
        spectral_weights(PAPER, observer="Stockman & Sharpe 2 Degree Cone Fundamentals")
    with pytest.raises(ConfigError, match=r"\(3,\)"):
        spectral_weights("450,550,650", np.ones(4))
    with pytest.raises(PhysicsRangeError, match=">= 0"):
        spectral_weights("450,550,650", np.array([1.0, -1.0, 1.0]))
    with pytest.raises(ConfigError, match="distinct"):
        spectral_weights([550.0, 550.0])
    with pytest.raises(PhysicsRangeError, match="luminance"):
        spectral_weights([1000.0, 1100.0])  # beyond the CMF table: no Y
    with pytest.raises(PhysicsRangeError, match="metres"):
        spectral_weights(5.5e-7)


# --------------------------------------------------------------------------- xyz_to_rgb


def test_d65_white_is_srgb_white():
    """XYZ of D65 (0.95047, 1, 1.08883) maps to linear sRGB (1, 1, 1) within 1e-3."""
    rgb = xyz_to_rgb(jnp.array([0.95047, 1.0, 1.08883]))
    np.testing.assert_allclose(np.asarray(rgb), 1.0, atol=1e-3)


@pytest.mark.parametrize("space", ["sRGB", "ITU-R BT.2020", "ACEScg"])
def test_xyz_to_rgb_leading_dims_match_colour(space):
    """Any leading dims; equals colour.XYZ_to_RGB without adaptation (rtol 1e-10, float64)."""
    xyz = np.random.default_rng(0).uniform(0.0, 1.0, (2, 4, 5, 3))
    with x64():
        rgb = np.asarray(xyz_to_rgb(jnp.asarray(xyz), space))
    assert rgb.shape == xyz.shape
    expected = colour.XYZ_to_RGB(xyz, space, illuminant=None, apply_cctf_encoding=False)
    np.testing.assert_allclose(rgb, expected, rtol=1e-10, atol=1e-12)


def test_xyz_to_rgb_keeps_float32():
    assert xyz_to_rgb(jnp.ones((3, 3), jnp.float32)).dtype == jnp.float32


def test_equal_energy_white_is_not_adapted():
    """Documented choice: no chromatic adaptation, so E (X = Y = Z) is pinkish in sRGB."""
    rgb = np.asarray(xyz_to_rgb(jnp.ones(3)))
    np.testing.assert_allclose(rgb, [1.2048, 0.9484, 0.9087], atol=1e-3)


def test_xyz_to_rgb_errors():
    with pytest.raises(ConfigError, match="sRGB") as info:
        xyz_to_rgb(jnp.ones(3), "sRGBB")
    assert "'sRGBB'" in str(info.value)
    with pytest.raises(ValueError, match="3 channels"):
        xyz_to_rgb(jnp.ones((4, 4)))


# --------------------------------------------------------------------------- psf_to_xyz


def test_psf_to_xyz_is_the_weighted_sum():
    rng = np.random.default_rng(1)
    psfs = rng.uniform(size=(3, 2, 8, 9))  # (wavelength, batch, h, w)
    w = spectral_weights("450,550,650", "D65")
    with x64():
        out = np.asarray(psf_to_xyz(jnp.asarray(psfs), w))
    expected = sum(psfs[i][..., None] * w[i] for i in range(3))
    np.testing.assert_allclose(out, expected, rtol=1e-12)
    with pytest.raises(ValueError, match=r"\(3, 3\)"):
        psf_to_xyz(jnp.asarray(psfs), w[:2])


# --------------------------------------------------------------------------- scale_psf


@pytest.mark.parametrize("npix", [32, 33])
def test_scale_by_one_is_identity(npix):
    psf = jnp.asarray(np.random.default_rng(2).uniform(size=(npix, npix)), jnp.float32)
    np.testing.assert_array_equal(np.asarray(scale_psf(psf, 1.0)), np.asarray(psf))


@pytest.mark.parametrize("npix", [32, 33])
@pytest.mark.parametrize("factor", [0.7, 1.3])
def test_centre_pixel_is_the_fixed_point(npix, factor):
    """A delta at (npix//2, npix//2) stays there with value 1 / factor^2 (rtol 1e-6)."""
    psf = jnp.zeros((npix, npix)).at[npix // 2, npix // 2].set(1.0)
    out = np.asarray(scale_psf(psf, factor))
    np.testing.assert_allclose(out[npix // 2, npix // 2], 1 / factor**2, rtol=1e-6)
    if factor > 1:  # magnification spreads it over neighbours; nothing lands off-axis rows
        assert np.all(out[: npix // 2 - 1] == 0) and np.all(out[npix // 2 + 2 :] == 0)


@pytest.mark.parametrize("shape", [(24, 24), (21, 30)])
@pytest.mark.parametrize("factor", [0.66, 1.137, 1.5])
def test_scale_matches_map_coordinates(shape, factor):
    """Separable gather == jax.scipy.ndimage.map_coordinates(order=1, cval=0) / f^2 (1e-12)."""
    psf = np.random.default_rng(3).uniform(size=shape)
    with x64():
        out = np.asarray(scale_psf(jnp.asarray(psf), factor))
        cy, cx = shape[0] // 2, shape[1] // 2
        yy, xx = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
        coords = [cy + (yy - cy) / factor, cx + (xx - cx) / factor]
        ref = np.asarray(map_coordinates(jnp.asarray(psf), coords, order=1, mode="constant"))
    np.testing.assert_allclose(out, ref / factor**2, rtol=1e-12, atol=1e-14)


def test_scale_conserves_energy():
    """Sum kept within 1e-3 for factors 0.7..1.3 (pattern inside the field).

    Measured worst case 2.1e-5 (factor 0.9); bilinear resampling of a smooth pattern.
    """
    psf = gaussians(128)
    with x64():
        sums = [float(scale_psf(jnp.asarray(psf), f).sum()) for f in np.linspace(0.7, 1.3, 7)]
    np.testing.assert_allclose(sums, 1.0, atol=1e-3)


def test_scale_reproduces_airy_at_each_wavelength():
    """Airy at 575 nm, 12 px per lambda/D, magnified by lambda / 575 == Airy at lambda.

    All 32 paper wavelengths; max |error| / peak < 1e-2. Measured: 7.5e-3 at the ends
    (380 and 758 nm), 0 at 575 nm. At 10 px per lambda/D it is 1.0e-2: bilinear error
    ~ (|I_xx| + |I_yy|) / 8 near the peak.
    """
    p = 12.0
    ref = airy(192, p)
    worst = 0.0
    with x64():
        for lam in parse_wavelengths(PAPER):
            f = lam / 575.0
            out = np.asarray(scale_psf(jnp.asarray(ref), f))
            exact = airy(192, p * f)
            worst = max(worst, np.abs(out - exact).max() / exact.max())
    print(f"max |scale_psf - Airy| / peak = {worst:.3g}")
    assert worst < 1e-2, worst


def test_scale_gradient_matches_finite_differences():
    """d/dfactor of a weighted sum, float64, at factors where no sample sits on a pixel centre."""
    rng = np.random.default_rng(4)
    with x64():
        psf = jnp.asarray(gaussians(40))
        mask = jnp.asarray(rng.uniform(size=(40, 40)))

        def objective(factor):
            return jnp.sum(scale_psf(psf, factor) * mask)

        for factor in (0.8317, 1.137):
            assert_grad_matches_fd(objective, factor, eps=1e-6, rtol=1e-5)


def test_scale_jit_vmap_and_batch_dims():
    rng = np.random.default_rng(5)
    psfs = jnp.asarray(rng.uniform(size=(3, 20, 20)), jnp.float32)
    factors = jnp.array([0.7, 1.0, 1.25], jnp.float32)
    eager = np.stack([np.asarray(scale_psf(p, 1.2)) for p in psfs])
    np.testing.assert_allclose(np.asarray(jax.jit(scale_psf)(psfs[0], 1.2)), eager[0], rtol=1e-6)
    np.testing.assert_allclose(
        np.asarray(jax.vmap(scale_psf, in_axes=(0, None))(psfs, 1.2)), eager, rtol=1e-6
    )
    np.testing.assert_allclose(np.asarray(scale_psf(psfs, 1.2)), eager, rtol=1e-6)
    per_factor = np.stack([np.asarray(scale_psf(psfs[0], f)) for f in factors])
    np.testing.assert_allclose(
        np.asarray(jax.vmap(scale_psf, in_axes=(None, 0))(psfs[0], factors)),
        per_factor,
        rtol=1e-6,
    )


def test_scale_errors():
    with pytest.raises(PhysicsRangeError, match="scale factor"):
        scale_psf(jnp.ones((4, 4)), 0.0)
    with pytest.raises(ValueError, match="2 dimensions"):
        scale_psf(jnp.ones(4), 1.0)


# --------------------------------------------------------------------------- scaled copies


def test_scaled_copies_equals_explicit_sum():
    """The scan equals a Python loop of scale_psf calls (float64, rtol 1e-12)."""
    wl = parse_wavelengths("420:700:5")
    w = spectral_weights(wl, "A")
    psf = gaussians(48)
    with x64():
        out = np.asarray(scaled_copies_xyz(jnp.asarray(psf), 575.0, wl, w))
        loop = sum(
            np.asarray(scale_psf(jnp.asarray(psf), lam / 575.0))[..., None] * w[i]
            for i, lam in enumerate(wl)
        )
    np.testing.assert_allclose(out, loop, rtol=1e-12, atol=1e-16)


@pytest.mark.parametrize("illuminant", ["E", "D65"])
def test_scaled_copies_match_exact_spectral_airy(illuminant):
    """32 scaled copies of the 575 nm Airy vs the sum of exact Airy PSFs at each wavelength.

    12 px per lambda/D at 575 nm; relative L2 error per XYZ channel < 1e-2. Measured:
    (3.2e-3, 3.2e-3, 4.8e-3) for both E and D65; at 10 px per lambda/D (4.5e-3, 4.3e-3, 6.8e-3).
    """
    p, n = 12.0, 192
    wl = parse_wavelengths(PAPER)
    w = spectral_weights(wl, illuminant)
    with x64():
        approx = np.asarray(scaled_copies_xyz(jnp.asarray(airy(n, p)), 575.0, wl, w))
        exact = np.asarray(psf_to_xyz(jnp.asarray([airy(n, p * lam / 575.0) for lam in wl]), w))
    err = np.linalg.norm(approx - exact, axis=(0, 1)) / np.linalg.norm(exact, axis=(0, 1))
    print(f"relative L2 error per XYZ channel ({illuminant}): {err}")
    assert np.all(err < 1e-2), err


def test_scaled_copies_jit_vmap_and_grad():
    wl = parse_wavelengths(PAPER)
    w = spectral_weights(wl, "D65")
    psfs = jnp.asarray(np.stack([gaussians(32), gaussians(32).T]), jnp.float32)
    loop = np.stack([np.asarray(scaled_copies_xyz(p, 575.0, wl, w)) for p in psfs])
    jitted = jax.jit(lambda p: scaled_copies_xyz(p, 575.0, wl, w))
    np.testing.assert_allclose(np.asarray(jitted(psfs[0])), loop[0], rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(np.asarray(jax.vmap(jitted)(psfs)), loop, rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(
        np.asarray(scaled_copies_xyz(psfs, 575.0, wl, w)), loop, rtol=1e-5, atol=1e-9
    )
    with x64():
        psf = jnp.asarray(gaussians(32))

        def objective(ref_nm):  # moving the reference wavelength rescales every copy
            return scaled_copies_xyz(psf, ref_nm, wl, w)[10:20, 10:20, 2].sum()

        assert_grad_matches_fd(objective, 571.3, eps=1e-4, rtol=1e-5)


def test_scaled_copies_errors():
    wl = parse_wavelengths(PAPER)
    with pytest.raises(ValueError, match=r"\(32, 3\)"):
        scaled_copies_xyz(jnp.ones((8, 8)), 575.0, wl, np.ones((31, 3)))
    with pytest.raises(PhysicsRangeError, match="metres"):
        scaled_copies_xyz(jnp.ones((8, 8)), 5.75e-7, wl, np.ones((32, 3)))


def test_d65_point_source_is_neutral_in_srgb():
    """A narrow unit-energy PSF under D65 light sums to linear sRGB (1, 1, 1) within 5e-3.

    Every copy stays inside the field, so the channel sums are the D65 white point of the
    32-sample weights (xy off by ~1e-4), mapped to sRGB.
    """
    rgb = spectral_psf_rgb(jnp.asarray(gaussians(64)), 575.0, PAPER, illuminant="D65")
    assert rgb.shape == (64, 64, 3)
    np.testing.assert_allclose(np.asarray(rgb.sum(axis=(0, 1))), 1.0, atol=5e-3)
