"""Tests of the render pipeline: bright pixels, convolution, billboards, tone maps, scenes.

References are independent numpy computations (explicit loops over pixels and PSF
taps, formulas written out again). Tolerances are in the test names or docstrings.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import assert_grad_converges, x64

from invglare.errors import ConfigError, InputDataError, PhysicsRangeError
from invglare.files import encode_srgb, read_exr
from invglare.files.depth_frames import read_frame_and_depth
from invglare.optics.spectral import scale_psf
from invglare.render import (
    DISPLAY_MAX,
    SCENES,
    TONEMAPS,
    BrightPixels,
    add_billboards,
    billboard_glare,
    bright_pixel_list,
    bright_pixels,
    check_compatible_scales,
    convolve_psf,
    display_to_unit,
    exposure_gamma,
    fft_size,
    kakimoto_glare_image,
    kakimoto_glare_layers,
    kakimoto_scene_scale,
    kakimoto_sigmoid,
    kakimoto_sigmoid_inverse,
    kakimoto_tonemap,
    linear_period,
    luminance,
    reinhard_global,
    resample_psf,
    srgb_display,
    srgb_encode,
    tonemap,
    validate_scene,
    write_scene,
)
from invglare.render.scenes import EYE_HEIGHT_M, SCENE_DEPTHS, SKY_DEPTH_M

REC709 = np.array([0.2126, 0.7152, 0.0722])


def direct_convolution(image: np.ndarray, psf: np.ndarray) -> np.ndarray:
    """Sum of shifted, scaled PSFs, one per image pixel, clipped at the frame (float64)."""
    img = image[..., None] if image.ndim == 2 else image
    ker = psf[..., None] if psf.ndim == 2 else psf
    big, small = img.shape[:2], ker.shape[:2]
    out = np.zeros((*big, max(img.shape[2], ker.shape[2])))
    for i in range(big[0]):
        for j in range(big[1]):
            for a in range(small[0]):
                for b in range(small[1]):
                    y, x = i + a - small[0] // 2, j + b - small[1] // 2
                    if 0 <= y < big[0] and 0 <= x < big[1]:
                        out[y, x] += img[i, j] * ker[a, b]
    return out[..., 0] if image.ndim == 2 and psf.ndim == 2 else out


def gaussian_psf(n: int, sigma: float) -> np.ndarray:
    c = np.arange(n) - n // 2
    g = np.exp(-(c[:, None] ** 2 + c[None, :] ** 2) / (2 * sigma**2))
    return g / g.sum()


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


# --------------------------------------------------------------------------- convolution


@pytest.mark.parametrize("psf_shape", [(7, 7), (8, 8), (5, 8), (15, 13)])
def test_convolution_equals_direct_sum_rel_1e5(rng, psf_shape):
    """FFT convolution of a 12x10 image = direct sum of shifted PSFs, to 1e-5 of the max."""
    image = rng.random((12, 10)).astype(np.float32)
    psf = rng.random(psf_shape).astype(np.float32)
    ref = direct_convolution(image.astype(float), psf.astype(float))
    out = np.asarray(convolve_psf(image, psf))
    assert out.shape == (12, 10) and out.dtype == np.float32
    np.testing.assert_allclose(out, ref, atol=1e-5 * ref.max(), rtol=0)


def test_convolution_rgb_psf_per_channel_and_mono_psf_on_rgb_rel_1e5(rng):
    """An (h, w, 3) PSF is applied channel by channel; an (h, w) one to every channel."""
    image = rng.random((12, 10, 3)).astype(np.float32)
    psf_rgb = rng.random((7, 8, 3)).astype(np.float32)
    out = np.asarray(convolve_psf(image, psf_rgb))
    for c in range(3):
        ref = direct_convolution(image[..., c].astype(float), psf_rgb[..., c].astype(float))
        np.testing.assert_allclose(out[..., c], ref, atol=1e-5 * ref.max(), rtol=0)
    mono = psf_rgb[..., 1]
    out = np.asarray(convolve_psf(image, mono))
    ref = direct_convolution(image.astype(float), mono.astype(float))
    assert out.shape == (12, 10, 3)
    np.testing.assert_allclose(out, ref, atol=1e-5 * ref.max(), rtol=0)
    # A mono image with an RGB PSF gives an RGB image.
    out = np.asarray(convolve_psf(image[..., 0], psf_rgb))
    ref = direct_convolution(image[..., 0].astype(float), psf_rgb.astype(float))
    assert out.shape == (12, 10, 3)
    np.testing.assert_allclose(out, ref, atol=1e-5 * ref.max(), rtol=0)


def test_convolution_preserves_energy_rtol_1e6(rng):
    """A PSF summing to 1 keeps the image sum when the image has a dark border (float64)."""
    with x64():
        image = np.zeros((40, 36))
        image[10:30, 10:26] = rng.random((20, 16)) * 1e4  # HDR values
        psf = gaussian_psf(17, 2.5)  # half-width 8 < the 10-pixel dark border
        out = convolve_psf(image, psf)
        np.testing.assert_allclose(float(out.sum()), image.sum(), rtol=1e-6)


def test_convolution_has_no_wrap_around():
    """A source on the left edge puts nothing on the right edge (< 1e-6 of the peak)."""
    image = np.zeros((16, 16), np.float32)
    image[8, 0] = 1.0
    psf = np.ones((9, 9), np.float32) / 81
    out = np.asarray(convolve_psf(image, psf))
    assert np.abs(out[:, -4:]).max() < 1e-6 * out.max()
    assert out[8, :5].min() > 0.9 / 81  # the light is where it should be
    # Without padding the convolution is circular: the light does wrap (so the test can fail).
    wrapped = np.asarray(convolve_psf(image, psf, pad=False))
    np.testing.assert_allclose(wrapped[4:13, -4:], 1 / 81, rtol=1e-5)


@pytest.mark.parametrize(("n_image", "n_psf"), [(12, 7), (12, 8), (9, 15), (10, 30), (6, 1)])
def test_linear_period_is_the_shortest_wrap_free_period(rng, n_image, n_psf):
    """The circular convolution over `linear_period` equals the direct sum (1e-10, float64);
    one sample shorter, light wraps onto the image (for even and odd PSFs, larger or not)."""
    from invglare.render.convolve import crop_psf_reach, wrap_psf

    image, psf = rng.random(n_image), rng.random(n_psf)
    ref = direct_convolution(image[:, None], psf[:, None])[:, 0]

    def circular(period):
        ker = crop_psf_reach(jnp.asarray(psf)[None, :, None], n_image, 1)
        ker = np.asarray(wrap_psf(ker, period, 1))[0, :, 0]
        full = np.fft.irfft(np.fft.rfft(image, period) * np.fft.rfft(ker), period)
        return full[:n_image]

    shortest = n_image + max(min(n_psf // 2, n_image - 1), min((n_psf - 1) // 2, n_image - 1))
    assert linear_period(n_image, n_psf) >= shortest
    np.testing.assert_allclose(circular(shortest), ref, atol=1e-10)
    if n_psf > 1:
        assert np.abs(circular(shortest - 1) - ref).max() > 1e-3
    assert linear_period(512, 512) == 768


def test_fft_size_is_smallest_235_smooth():
    def smooth(m):
        for p in (2, 3, 5):
            while m % p == 0:
                m //= p
        return m == 1

    for n in [1, 7, 17, 97, 1025, 2047]:
        m = fft_size(n)
        assert m >= n and smooth(m)
        assert not any(smooth(k) for k in range(n, m))
        even = fft_size(n, even=True)  # the holographic eye's cropped grids
        assert even >= n and even % 2 == 0 and smooth(even)
        assert not any(smooth(k) for k in range(n, even) if k % 2 == 0)


def test_resample_psf_energy_and_width():
    """Downscaling keeps energy exactly (1e-6) even for a one-pixel core; width scales (2 %)."""
    with x64():
        psf = gaussian_psf(101, 6.0) * 0.3
        psf[50, 50] += 0.7  # a one-pixel core, the hard case for point-sampled decimation
        coarse = resample_psf(psf, 0.005, 0.02, 51)
        assert coarse.shape == (51, 51)
        np.testing.assert_allclose(float(coarse.sum()), 1.0, rtol=1e-6)
        assert int(jnp.argmax(coarse)) == 25 * 51 + 25  # centre stays at npix // 2

        smooth = gaussian_psf(61, 6.0)
        for from_deg, to_deg in [(0.01, 0.02), (0.01, 0.013), (0.02, 0.01), (0.01, 0.007)]:
            out = np.asarray(resample_psf(smooth, from_deg, to_deg, 121))
            np.testing.assert_allclose(out.sum(), 1.0, rtol=1e-3)
            c = np.arange(121) - 60
            sigma = np.sqrt((out * c[None, :] ** 2).sum() / out.sum())
            np.testing.assert_allclose(sigma, 6.0 * from_deg / to_deg, rtol=0.02)
        np.testing.assert_allclose(resample_psf(smooth, 0.01, 0.01, 61), smooth, atol=1e-15)
        rgb = np.stack([smooth, 2 * smooth, 3 * smooth], -1)
        out = resample_psf(rgb, 0.01, 0.02, 31)
        assert out.shape == (31, 31, 3)
        np.testing.assert_allclose(out[..., 2], 3 * resample_psf(smooth, 0.01, 0.02, 31))


def test_resample_psf_traced_scales_match_eager():
    """Under jit the branch is a lax.cond; both directions equal the eager result (1e-6)."""
    psf = gaussian_psf(41, 3.0).astype(np.float32)
    f = jax.jit(resample_psf, static_argnums=3)
    for to_deg in (0.005, 0.02):
        np.testing.assert_allclose(
            f(psf, 0.01, to_deg, 41), resample_psf(psf, 0.01, to_deg, 41), atol=1e-6
        )


# --------------------------------------------------------------------------- bright pixels


def test_bright_pixels_threshold_semantics():
    """Pixels at or above the luminance threshold are kept whole; the rest become 0."""
    image = np.zeros((4, 5, 3), np.float32)
    image[0, 0] = [3000.0, 3000.0, 3000.0]  # L = 3000
    image[1, 1] = [1000.0, 1000.0, 1000.0]  # L = 1000, exactly the threshold: kept
    image[2, 2] = [4000.0, 0.0, 0.0]  # bright red, L = 850.4: removed
    image[3, 3] = [0.0, 1500.0, 0.0]  # L = 1072.8: kept
    out = np.asarray(bright_pixels(image, 1000.0))
    expected = image.copy()
    expected[2, 2] = 0
    np.testing.assert_array_equal(out, expected)
    # Mono images are thresholded on their value.
    np.testing.assert_array_equal(
        np.asarray(bright_pixels(np.array([[1.0, 5.0]]), 2.0)), [[0.0, 5.0]]
    )
    # Soft version: weight 1/2 at the threshold, ~1 a decade above, ~0 a decade below.
    soft = np.asarray(bright_pixels(np.array([[100.0, 1000.0, 10000.0]]), 1000.0, softness=0.1))
    np.testing.assert_allclose(soft, [[0.0, 500.0, 10000.0]], atol=1e-6 * 1e4)
    np.testing.assert_allclose(np.asarray(luminance(image))[2, 2], 4000 * 0.2126, rtol=1e-6)


def test_bright_pixel_list_top_k_under_jit():
    """The list holds the brightest pixels first, with exact positions and values."""
    image = np.full((6, 7, 3), 1.0, np.float32)
    spots = {(0, 6): 9e3, (5, 0): 4e3, (2, 3): 7e3, (4, 4): 2e3, (3, 1): 5e3}
    for (r, c), v in spots.items():
        image[r, c] = [v, v, v]
    f = jax.jit(bright_pixel_list, static_argnums=2)
    bp = f(image, 1000.0, 8)
    assert isinstance(bp, BrightPixels)
    order = sorted(spots, key=spots.get, reverse=True)
    assert np.asarray(bp.valid).tolist() == [True] * 5 + [False] * 3
    assert list(zip(np.asarray(bp.rows)[:5], np.asarray(bp.cols)[:5], strict=True)) == order
    np.testing.assert_array_equal(np.asarray(bp.values)[:5, 0], [spots[p] for p in order])
    np.testing.assert_array_equal(np.asarray(bp.values)[5:], 0)  # invalid slots are zero
    assert int(bp.n_above) == 5
    eager = bright_pixel_list(image, 1000.0, 8)
    for a, b in zip(bp, eager, strict=True):
        np.testing.assert_array_equal(a, b)
    # Truncated list: the three brightest, and n_above says five were above the threshold.
    short = f(image, 1000.0, 3)
    assert np.asarray(short.valid).all() and int(short.n_above) == 5
    assert np.asarray(short.values).shape == (3, 3)
    # Mono image: values are (N,).
    assert bright_pixel_list(image[..., 0], 1000.0, 4).values.shape == (4,)


# --------------------------------------------------------------------------- billboards


def test_billboards_equal_direct_sum_and_convolution_rel_1e5(rng):
    """Billboards = direct sum over the listed pixels = convolve_psf(bright_pixels(...))."""
    image = rng.random((12, 10, 3)).astype(np.float32)
    image[rng.random((12, 10)) > 0.8] *= 1e3  # about 24 bright pixels, some at the edges
    image[0, 0] = image[11, 9] = 2e3  # stamps that overhang two corners
    threshold = 100.0
    bp = bright_pixel_list(image, threshold, 12 * 10)
    assert int(bp.n_above) == int(np.asarray(bp.valid).sum())  # every bright pixel listed
    bright = np.asarray(bright_pixels(image, threshold))
    for psf in (rng.random((7, 7)), rng.random((8, 6, 3))):
        psf = psf.astype(np.float32)
        glare = np.asarray(billboard_glare(bp, psf, (12, 10)))
        ref = direct_convolution(bright.astype(float), psf.astype(float))
        np.testing.assert_allclose(glare, ref, atol=1e-5 * ref.max(), rtol=0)
        conv = np.asarray(convolve_psf(bright, psf))
        np.testing.assert_allclose(glare, conv, atol=1e-5 * ref.max(), rtol=0)
    out = np.asarray(add_billboards(image, bp, psf))
    np.testing.assert_allclose(out, image + glare, rtol=1e-6)


def test_billboards_per_position_psf_and_invalid_entries(rng):
    """A PSF bank indexed per billboard; invalid or out-of-frame entries add nothing (1e-6)."""
    psfs = rng.random((3, 5, 5)).astype(np.float32)
    bp = BrightPixels(
        rows=jnp.array([0, 4, 2, 3, 99]),
        cols=jnp.array([1, 5, 3, 3, 0]),
        values=jnp.array([10.0, 20.0, 30.0, 1e9, 1e9]),
        valid=jnp.array([True, True, True, False, True]),  # the last one is outside the frame
        n_above=jnp.array(4),
    )
    out = np.asarray(billboard_glare(bp, psfs, (6, 7), psf_index=jnp.array([2, 0, 1, 1, 0])))
    ref = np.zeros((6, 7))
    for r, c, v, k in [(0, 1, 10.0, 2), (4, 5, 20.0, 0), (2, 3, 30.0, 1)]:
        one = np.zeros((6, 7))
        one[r, c] = v
        ref += direct_convolution(one, psfs[k].astype(float))
    assert out.shape == (6, 7)
    np.testing.assert_allclose(out, ref, rtol=1e-6, atol=1e-6 * ref.max())


# --------------------------------------------------------------------------- tone maps


def test_kakimoto_sigmoid_formula_limits_and_monotonic_rel_1e6():
    """eq. 7 at a few x; D/k at 0, D at infinity; increasing; inverse round trip."""
    with x64():
        x = np.array([0.0, 1e-3, 0.5, 1.0, 10.0, 194.0, 1e4])
        D, k, g = 640.0, 20.0, 0.465
        ref = (x**g + 1) / (x**g + k) * D
        np.testing.assert_allclose(kakimoto_sigmoid(x), ref, rtol=1e-12)
        np.testing.assert_allclose(kakimoto_sigmoid(1.0), 640 * 2 / 21, rtol=1e-12)
        assert float(kakimoto_sigmoid(0.0)) == pytest.approx(D / k, rel=1e-12)
        assert float(kakimoto_sigmoid(1e40)) == pytest.approx(D, rel=1e-6)
        other = kakimoto_sigmoid(x, D=300.0, k=5.0, g=0.8)
        np.testing.assert_allclose(other, (x**0.8 + 1) / (x**0.8 + 5) * 300, rtol=1e-12)
        grid = np.logspace(-6, 8, 200)
        assert np.all(np.diff(np.asarray(kakimoto_sigmoid(grid))) > 0)
        y = np.array([40.0, 100.0, DISPLAY_MAX, 600.0])
        np.testing.assert_allclose(kakimoto_sigmoid(kakimoto_sigmoid_inverse(y)), y, rtol=1e-10)
        assert float(kakimoto_sigmoid_inverse(DISPLAY_MAX)) == pytest.approx(194.0, rel=0.01)
        np.testing.assert_array_equal(display_to_unit(np.array([-5.0, 127.5, 640.0])), [0, 0.5, 1])
        np.testing.assert_allclose(
            kakimoto_tonemap(np.array([[0.0, 100.0]]), scale=2.0),
            np.clip(np.array([[32.0, (200**g + 1) / (200**g + k) * D]]) / 255, 0, 1),
            rtol=1e-12,
        )


def test_kakimoto_glare_layers_split_and_display():
    """spot + glare == psf (rtol 1e-6); spot only inside the radius; display in [D/k/255, 1]."""
    psf = (gaussian_psf(33, 1.0) + 1e-4 * gaussian_psf(33, 8.0)).astype(np.float32)
    psf_rgb = np.stack([psf, 0.5 * psf, 0.25 * psf], -1)
    for p in (psf, psf_rgb):
        layers = kakimoto_glare_layers(p, 3.0)
        np.testing.assert_allclose(np.asarray(layers.spot + layers.glare), p, rtol=1e-6)
        np.testing.assert_array_equal(np.asarray(layers.glare), np.minimum(p, layers.clip_level))
        c = np.arange(33) - 16
        outside = (c[:, None] ** 2 + c[None, :] ** 2) > 9
        assert np.all(np.asarray(layers.spot)[outside] == 0)
        assert float(layers.clip_level) == pytest.approx(p[outside].max())
        img = np.asarray(kakimoto_glare_image(p, 3.0))
        assert img.shape == p.shape and img.max() == pytest.approx(1.0)
        assert img.min() >= 32 / 255 - 1e-6
    with pytest.raises(PhysicsRangeError, match="spot_radius_px"):
        kakimoto_glare_layers(psf, 40.0)


def test_kakimoto_scene_scale_shows_each_light_as_its_glare_image():
    """A light of value v rendered with a PSF and tone-mapped at the scene scale of the
    brightest light v_max is kakimoto_glare_image(psf) at input scale v / v_max (rtol 1e-5)."""
    psf = (gaussian_psf(33, 1.0) + 1e-4 * gaussian_psf(33, 8.0)).astype(np.float32)
    bright, dim = 5e4, 5e3
    scale = kakimoto_scene_scale(psf, 3.0, bright)
    np.testing.assert_allclose(
        kakimoto_tonemap(bright * psf, scale), kakimoto_glare_image(psf, 3.0), rtol=1e-5
    )
    # The dimmer light: its glare plateau sits a factor 10 lower on the curve's input.
    layers = kakimoto_glare_layers(psf, 3.0)
    white = kakimoto_sigmoid_inverse(255.0)
    expected = display_to_unit(kakimoto_sigmoid(psf / layers.clip_level * white * (dim / bright)))
    np.testing.assert_allclose(kakimoto_tonemap(dim * psf, scale), expected, rtol=1e-5)
    with pytest.raises(PhysicsRangeError, match="light_value"):
        kakimoto_scene_scale(psf, 3.0, 0.0)


def test_reinhard_global_values_rel_1e6(rng):
    """L_d = L_m / (1 + L_m) with L_m = key L / L_avg; white maps to exactly 1."""
    with x64():
        rgb = rng.random((8, 9, 3)) * np.logspace(-1, 4, 9)[None, :, None]
        lum = rgb @ REC709
        l_avg = np.exp(np.mean(np.log(1e-6 + lum)))
        lm = 0.18 * lum / l_avg
        out = np.asarray(reinhard_global(rgb, key=0.18))
        np.testing.assert_allclose(out @ REC709, lm / (1 + lm), rtol=1e-10)
        np.testing.assert_allclose(out, rgb * (lm / (1 + lm) / lum)[..., None], rtol=1e-10)
        mono = np.asarray(reinhard_global(lum, key=0.36))
        lm2 = 0.36 * lum / l_avg
        np.testing.assert_allclose(mono, lm2 / (1 + lm2), rtol=1e-10)
        white = float(lum[3, 4])
        with_white = np.asarray(reinhard_global(rgb, key=0.18, white=white)) @ REC709
        assert with_white[3, 4] == pytest.approx(1.0, rel=1e-10)
        lw = 0.18 * white / l_avg
        np.testing.assert_allclose(with_white, lm * (1 + lm / lw**2) / (1 + lm), rtol=1e-10)
        assert np.asarray(reinhard_global(np.zeros((2, 2, 3)))).max() == 0  # no NaN at black


def test_gamma_and_srgb_match_formulas():
    """exposure_gamma is clip(e x)^(1/gamma); srgb_encode equals the numpy io curve (1e-6)."""
    x = np.array([0.0, 0.001, 0.0031308, 0.05, 0.18, 0.5, 1.0, 3.0], np.float32)
    np.testing.assert_allclose(srgb_encode(x), encode_srgb(x), rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(
        exposure_gamma(x, exposure=2.0, gamma=2.2), np.clip(2 * x, 0, 1) ** (1 / 2.2), rtol=1e-6
    )
    np.testing.assert_allclose(srgb_display(x, 0.5), encode_srgb(np.clip(0.5 * x, 0, 1)), rtol=1e-6)


def test_tonemap_registry_outputs_display_range(rng):
    """Every registered map takes an HDR image to [0, 1] with the same shape."""
    hdr = (rng.random((6, 5, 3)) * 1e4).astype(np.float32)
    assert set(TONEMAPS) == {"kakimoto", "reinhard", "gamma", "srgb"}
    for name in TONEMAPS:
        out = np.asarray(tonemap(hdr, name))
        assert out.shape == hdr.shape and np.all((out >= 0) & (out <= 1))
    np.testing.assert_array_equal(tonemap(hdr, "gamma", exposure=1e-4), exposure_gamma(hdr, 1e-4))


# --------------------------------------------------------------------------- gradients, jit, vmap


def test_grad_convolution_wrt_psf_magnification_fd_rtol_1e5():
    """d/ds sum(w * convolve(image, scale_psf(psf, s))) against central differences (float64)."""
    with x64():
        rng = np.random.default_rng(3)
        image = rng.random((10, 11, 3))
        weights = rng.random((10, 11, 3))
        psf = gaussian_psf(9, 1.5)

        def f(s):
            return jnp.sum(weights * convolve_psf(image, scale_psf(psf, s)))

        # At a step of 1e-3 of s the truncation error is 3.7e-6 of the derivative (measured).
        assert_grad_converges(jax.jit(f), 1.23, 1.23e-3, rtol=1e-5)


@pytest.mark.parametrize(
    ("name", "fn", "x0"),
    [
        ("kakimoto D", lambda p, x: kakimoto_sigmoid(x, D=p), 640.0),
        ("kakimoto k", lambda p, x: kakimoto_sigmoid(x, k=p), 20.0),
        ("kakimoto g", lambda p, x: kakimoto_sigmoid(x, g=p), 0.465),
        ("kakimoto scale", lambda p, x: kakimoto_tonemap(x, scale=p), 0.003),
        ("reinhard key", lambda p, x: reinhard_global(x, key=p), 0.18),
        ("reinhard white", lambda p, x: reinhard_global(x, white=p), 5e3),
        ("gamma exposure", lambda p, x: exposure_gamma(x, exposure=p), 1e-4),
        ("gamma gamma", lambda p, x: exposure_gamma(x, exposure=1e-4, gamma=p), 2.2),
        ("srgb exposure", lambda p, x: srgb_display(x, exposure=p), 1e-4),
        ("soft threshold", lambda p, x: bright_pixels(x, p, softness=0.3), 3e3),
        ("resample down", lambda p, x: resample_psf(x[..., 0], 0.01, p, 9), 0.023),
        ("resample up", lambda p, x: resample_psf(x[..., 0], 0.01, p, 9), 0.0071),
    ],
)
def test_grad_tonemaps_wrt_parameters_fd_rtol_1e5(name, fn, x0):
    """Autodiff derivative of a weighted sum of the output = central difference (float64)."""
    with x64():
        rng = np.random.default_rng(5)
        hdr = rng.random((7, 7, 3)) * np.logspace(0, 4, 7)[None, :, None]
        weights = rng.random(fn(jnp.float64(x0), hdr).shape)
        # Steps of 1e-3 of each value: truncation errors up to 2e-6 of the derivative
        # (measured; none where the output is linear in the parameter).
        assert_grad_converges(
            jax.jit(lambda p: jnp.sum(weights * fn(p, hdr))), x0, 1e-3 * x0, rtol=1e-5, err_msg=name
        )


def test_jit_equals_eager_and_vmap_equals_loop_rel_1e6(rng):
    """Convolution, billboards and tone maps: jit = eager, vmap over 3 images = a loop."""
    images = (rng.random((3, 9, 8, 3)) * 1e3).astype(np.float32)
    psf = rng.random((5, 5, 3)).astype(np.float32)

    def pipeline(img):
        bp = bright_pixel_list(img, 500.0, 16)
        glare = convolve_psf(bright_pixels(img, 500.0), psf) + billboard_glare(bp, psf, (9, 8))
        return tonemap(img + glare, "reinhard"), kakimoto_tonemap(img + glare, scale=0.1)

    eager = [pipeline(im) for im in images]
    jitted = jax.jit(pipeline)
    for im, ref in zip(images, eager, strict=True):
        for a, b in zip(jitted(im), ref, strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    batched = jax.jit(jax.vmap(pipeline))(images)
    for i, ref in enumerate(eager):
        for a, b in zip(batched, ref, strict=True):
            np.testing.assert_allclose(a[i], b, rtol=1e-5, atol=1e-6)


# --------------------------------------------------------------------------- bad input


def test_validate_scene_reports_bad_pixels():
    good = np.ones((4, 5, 3), np.float32)
    assert validate_scene(good) is not None
    bad = good.copy()
    bad[1, 2, 1] = np.nan
    bad[3, 0, 0] = np.inf
    with pytest.raises(InputDataError, match=r"2 non-finite .*1 NaN, 1 Inf.*row 1, column 2"):
        validate_scene(bad)
    neg = good.copy()
    neg[2, 3, 2] = -0.5
    neg[3, 4, 0] = -2.0
    with pytest.raises(
        InputDataError, match=r"2 negative .*minimum -2.*row 2, column 3, channel 'B'"
    ):
        validate_scene(neg, name="photo.exr")
    for shape in [(5,), (2, 3, 4, 3), (0, 4)]:
        with pytest.raises(InputDataError, match=r"\(H, W\)"):
            validate_scene(np.ones(shape))


def test_incompatible_scales_and_unknown_names_raise():
    check_compatible_scales(0.02, 0.02 * (1 + 5e-4))  # within rtol 1e-3
    with pytest.raises(InputDataError, match=r"0\.01 deg/px.*0\.02 deg/px"):
        check_compatible_scales(0.02, 0.01)
    with pytest.raises(InputDataError, match="unknown"):
        check_compatible_scales(None, 0.01)
    with pytest.raises(PhysicsRangeError, match=r"-0\.01"):
        check_compatible_scales(-0.01, 0.01)
    # convolve_psf checks the scales it is given before it convolves.
    image, psf = np.ones((6, 6)), np.ones((3, 3)) / 9
    with pytest.raises(InputDataError, match=r"0\.01 deg/px.*0\.02 deg/px"):
        convolve_psf(image, psf, pixel_scales_deg=(0.02, 0.01))
    np.testing.assert_allclose(
        convolve_psf(image, psf, pixel_scales_deg=(0.02, 0.02)), convolve_psf(image, psf)
    )
    with pytest.raises(ConfigError, match=r"'filmic'.*kakimoto, reinhard, gamma, srgb"):
        tonemap(np.ones((2, 2)), "filmic")
    with pytest.raises(ConfigError, match=r"'gama'.*exposure, gamma"):
        tonemap(np.ones((2, 2)), "gamma", gama=2.4)
    with pytest.raises(ConfigError, match="candle"):
        write_scene("moon", "never.exr")
    with pytest.raises(InputDataError, match="2 channels"):
        convolve_psf(np.ones((4, 4, 2)), np.ones((3, 3, 3)))
    with pytest.raises(InputDataError, match="max_count"):
        bright_pixel_list(np.ones((2, 2)), 1.0, 5)
    with pytest.raises(PhysicsRangeError, match="threshold"):
        bright_pixels(np.ones((2, 2)), -1.0)
    with pytest.raises(PhysicsRangeError, match="gamma"):
        exposure_gamma(np.ones(2), gamma=0.0)


# --------------------------------------------------------------------------- scenes


@pytest.mark.parametrize("name", sorted(SCENES))
def test_scenes_are_plausible_hdr(name):
    """float32 RGB, finite, > 0, max/median luminance > 1e3, deterministic per seed."""
    image, scale = SCENES[name](64, 0)
    arr = np.asarray(image)
    assert arr.shape == (64, 64, 3) and arr.dtype == np.float32
    assert 0.01 <= scale <= 0.05
    validate_scene(arr)
    assert arr.min() > 0
    lum = arr @ REC709
    assert lum.max() / np.median(lum) > 1e3
    np.testing.assert_array_equal(np.asarray(SCENES[name](64, 0)[0]), arr)
    assert not np.array_equal(np.asarray(SCENES[name](64, 1)[0]), arr)


def test_scene_luminance_levels():
    """The light sources have the documented luminances (cd/m^2, within a factor of 3)."""
    street = np.asarray(SCENES["street_lights_at_night"](128, 0)[0]) @ REC709
    assert 3e3 < street.max() < 3e4 and np.median(street) < 1.0
    sun = np.asarray(SCENES["sunlit_specular_highlight"](128, 0)[0]) @ REC709
    assert 1e6 < sun.max() < 1e7 and 3e2 < np.median(sun) < 3e3
    flame = np.asarray(SCENES["candle"](128, 0)[0]) @ REC709
    assert 2e3 < flame.max() < 1e4 and 0.3 < np.median(flame) < 3


def test_write_scene_exr_round_trip(tmp_path):
    path = write_scene("candle", tmp_path / "candle.exr", npix=48, seed=2)
    exr = read_exr(path)
    image, scale = SCENES["candle"](48, 2)
    np.testing.assert_array_equal(exr.data, np.asarray(image))
    assert exr.channels == ("R", "G", "B")
    assert exr.pixel_scale_deg == scale
    assert exr.attrs["invglareScene"] == "candle"


@pytest.mark.parametrize("name", sorted(SCENES))
def test_scene_depth_buffers(tmp_path, name):
    """Every scene's depth: float32 metres, finite, from 0.5 m to the sky's 1000 m, the same
    for every seed, written as a Z channel at the scene's pixel scale beside it."""
    depth = np.asarray(SCENE_DEPTHS[name](64))
    assert depth.shape == (64, 64) and depth.dtype == np.float32
    assert np.all(np.isfinite(depth)) and 0.5 <= depth.min() and depth.max() <= SKY_DEPTH_M
    assert len(np.unique(depth)) > 3  # not one constant depth
    write_scene(name, tmp_path / "s.exr", npix=64, seed=3, depth_path=tmp_path / "z.exr")
    got = read_frame_and_depth(tmp_path / "s.exr", tmp_path / "z.exr")
    np.testing.assert_array_equal(got.depth, depth)
    assert read_exr(tmp_path / "z.exr").channels == ("Z",)
    assert got.pixel_scale_deg == SCENES[name](64, 3)[1]


def test_street_depth_follows_the_ground_and_the_lamp_sizes():
    """The road's planar depth is the eye's height over tan(angle below the horizon), the
    bottom row of 256 at 0.05 deg/px 13 m away; a lamp head of 0.4 m subtending 1 deg is
    22.9 m away (0.2 / tan 0.5 deg)."""
    depth = np.asarray(SCENE_DEPTHS["street_lights_at_night"](256))
    horizon, scale = 0.45 * 256, 0.05
    rows = np.arange(200, 256)
    expected = EYE_HEIGHT_M / np.tan(np.radians((rows - horizon + 0.5) * scale))
    np.testing.assert_allclose(depth[rows, 20], expected, rtol=1e-5)
    assert depth[-1, 20] == pytest.approx(13.0, abs=0.05)
    nearest_lamp = (round(0.12 * 256), round(0.08 * 256))
    assert depth[nearest_lamp] == pytest.approx(0.2 / np.tan(np.radians(0.5)), rel=1e-5)
    assert depth[0, 128] == SKY_DEPTH_M


def test_reinhard_treats_negative_out_of_gamut_luminance_as_black():
    """A spectral PSF's out-of-gamut pixels can have luminance < 0: no NaN, no white-out."""
    from invglare.render.tonemap import reinhard_global

    image = np.full((8, 8, 3), 1.0, np.float32)
    image[2, 3] = [-500.0, 10.0, -300.0]  # luminance -150
    out = np.asarray(reinhard_global(image))
    assert np.all(np.isfinite(out))
    # Elsewhere the display values are those of the image with that pixel black.
    mask = np.ones((8, 8), bool)
    mask[2, 3] = False
    np.testing.assert_allclose(out[mask], np.asarray(reinhard_global(np.where(
        mask[..., None], image, 0.0)))[mask], rtol=1e-6)  # fmt: skip
