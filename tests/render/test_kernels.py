"""Kernels for renderers: each tool's convolution, re-implemented from its documentation and
source, applied to the exported kernel, gives `invglare render`'s frame (`convolve_psf`).

`blender_convolve` follows Blender's `compositor/algorithms/intern/convolve.cc` (the routine
of the Glare node's Kernel type and of the Convolve node): images kept bottom row first,
kernel centre ``size // 2``, the kernel written at ``centre - offset`` (a gather), zero
padding to ``image + max(kernel, image) - 1``, each channel optionally divided by its sum.
`blender_glare_output` adds the Glare node around it (`node_composite_glare.cc`: highlights
as HSV value minus the threshold, the kernel always normalised, the Glare output times
tint and strength, the Image output the input plus that). `unreal_bloom` follows Unreal's
`FConvolutionBloomSettings` (kernel centre at UV (0.5, 0.5), Convolution Scale relative to
the viewport's minor axis, a padded FFT convolution) with the kernel's total normalised to 1
(the reading of :mod:`invglare.render.kernels`).

Tolerances: the re-implementations run in float64, `convolve_psf` in float32 (rounding
~1e-7 of the largest value, plus FFT round-off that grows with the frame's dynamic range);
1e-5 of the frame's largest value holds with margin.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import OpenEXR
import pytest

from invglare.errors import ConfigError, InputDataError, PhysicsRangeError
from invglare.files.exr import write_exr
from invglare.render.convolve import convolve_psf
from invglare.render.kernels import (
    TARGETS,
    blender_kernel,
    centre_fraction,
    centred,
    channel_energy,
    check_kernel_request,
    kernel_for,
    luminance_energy,
    peak_offset_px,
    rgb,
    unreal_convolution_scale,
    unreal_kernel,
    viewport_pixel_scale_deg,
)

RTOL = 1e-5  # of the frame's largest value (see the module docstring)


# ------------------------------------------------------------------ the tools, re-implemented


def blender_convolve(image: np.ndarray, kernel: np.ndarray, normalize: bool) -> np.ndarray:
    """Blender's convolve.cc on (H, W, 3) images, in float64, as the file's rows."""
    # Blender's buffers are bottom row first: the file's row r is Blender's row H - 1 - r.
    img = np.asarray(image, np.float64)[::-1]
    ker = np.asarray(kernel, np.float64)[::-1]
    (hh, ww), (kh, kw) = img.shape[:2], ker.shape[:2]
    sy, sx = hh + max(kh, hh) - 1, ww + max(kw, ww) - 1
    cy, cx = kh // 2, kw // 2
    # buffer[t] = kernel[(centre - t) mod size], zero outside the kernel.
    ty, tx = np.arange(sy)[:, None], np.arange(sx)[None, :]
    ky, kx = (cy - ty) % sy, (cx - tx) % sx
    inside = (ky < kh) & (kx < kw)
    buf = np.where(inside[..., None], ker[np.minimum(ky, kh - 1), np.minimum(kx, kw - 1)], 0.0)
    total = ker.sum(axis=(0, 1))
    scale = np.where(total == 0, 1.0, total) if normalize else np.ones(3)
    spec = np.fft.rfft2(img, s=(sy, sx), axes=(0, 1)) * np.fft.rfft2(buf, axes=(0, 1))
    out = np.fft.irfft2(spec, s=(sy, sx), axes=(0, 1))[:hh, :ww] / scale
    return out[::-1]


def blender_glare_output(
    image: np.ndarray, kernel: np.ndarray, threshold: float, strength: float, tint
) -> tuple[np.ndarray, np.ndarray]:
    """The Glare node, type Kernel, Quality High, Saturation 1: (Glare output, Image output).

    Highlights: the HSV value less the threshold, hue and saturation kept, i.e. RGB scaled
    by ``max(V - t, 0) / V`` (the adaptive smooth clamp has no smoothing at the lower bound
    when the threshold is 0, the case used here).
    """
    img = np.asarray(image, np.float64)
    value = img.max(axis=-1, keepdims=True)
    factor = np.where(
        value > 0, np.maximum(value - threshold, 0.0) / np.where(value > 0, value, 1), 0
    )
    glare = blender_convolve(img * factor, kernel, normalize=True)
    glare = glare * np.asarray(tint, np.float64) * strength
    return glare, np.maximum(img, 0.0) + glare


def unreal_bloom(image: np.ndarray, texture: np.ndarray, size: float, viewport) -> np.ndarray:
    """Unreal's convolution bloom for a kernel texture at one texel per screen pixel."""
    n = texture.shape[0]
    centre_uv = ((np.arange(n) + 0.5) / n)[n // 2]
    assert centre_uv == 0.5, "Convolution Center (0.5, 0.5) must be a texel's centre"
    texels_per_px = n / (size * min(viewport))
    assert math.isclose(texels_per_px, 1.0, rel_tol=1e-6), (
        "the test drives the engine at one texel per pixel"
    )
    ker = np.asarray(texture, np.float64)
    ker = ker / ker.sum(axis=(0, 1))  # the kernel's total taken as all of the light
    img = np.asarray(image, np.float64)
    (hh, ww), c = img.shape[:2], n // 2
    # An FFT convolution with the kernel's centre at the origin of a padded buffer (the
    # Convolution Buffer keeps the bloom from wrapping): a spread, out[x] = sum in[u] K[c+x-u].
    sy, sx = hh + n, ww + n
    buf = np.zeros((sy, sx, 3))
    rows, cols = (np.arange(n) - c) % sy, (np.arange(n) - c) % sx
    buf[rows[:, None], cols[None, :]] = ker
    spec = np.fft.rfft2(img, s=(sy, sx), axes=(0, 1)) * np.fft.rfft2(buf, axes=(0, 1))
    return np.fft.irfft2(spec, s=(sy, sx), axes=(0, 1))[:hh, :ww]


# ------------------------------------------------------------------ a frame and a PSF


def _frame(h: int = 40, w: int = 52) -> np.ndarray:
    """An HDR RGB frame: a dim textured background and a few lights of different colours."""
    rng = np.random.default_rng(3)
    frame = 0.05 * rng.random((h, w, 3))
    for (r, c), colour in zip(
        [(5, 7), (20, 30), (33, 48), (39, 0)],
        [(1e3, 800, 600), (50, 90, 200), (1, 1, 1), (400, 0, 20)],
    ):
        frame[r, c] = colour
    return frame.astype(np.float32)


def _psf(n: int = 21) -> np.ndarray:
    """A tinted PSF without point symmetry: a core, a halo and a streak to the right and up.

    Channel energies 0.9, 0.8 and 0.7 (the rest 'fell outside the field'), so per-channel
    normalisation visibly changes its colour.
    """
    c = n // 2
    y, x = np.mgrid[:n, :n] - c
    core = np.exp(-(x**2 + y**2) / 1.5)
    halo = 0.02 * np.exp(-np.hypot(x, y) / 4.0)
    streak = np.where((y == -1) & (x > 0), 0.05 / np.maximum(1 + x, 1), 0.0)
    psf = np.stack([core + halo * s + streak * s for s in (1.0, 1.6, 2.2)], axis=-1)
    return (psf / psf.sum(axis=(0, 1)) * np.array([0.9, 0.8, 0.7])).astype(np.float32)


def _max_err(a, b) -> float:
    return float(np.max(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64))))


def _render(frame, psf) -> np.ndarray:
    """What `invglare render --mode convolve` computes for this frame and PSF."""
    return np.asarray(convolve_psf(jnp.asarray(frame), jnp.asarray(psf)), np.float64)


# ------------------------------------------------------------------ Blender


def test_blender_convolve_without_normalisation_is_invglare_render():
    frame, psf = _frame(), _psf()
    expected = _render(frame, psf)
    got = blender_convolve(frame, np.asarray(blender_kernel(psf)), normalize=False)
    assert _max_err(got, expected) <= RTOL * expected.max()


def test_blender_kernel_must_be_point_reflected():
    # Blender gathers: the PSF as it is (the Unreal layout) puts the streak on the wrong side.
    frame, psf = _frame(), _psf()
    expected = _render(frame, psf)
    wrong = blender_convolve(frame, np.asarray(unreal_kernel(psf)), normalize=False)
    assert _max_err(wrong, expected) > 100 * RTOL * expected.max()


def test_blender_even_kernel_is_a_row_off():
    # Why the size must be odd: an even kernel's centre row moves by one in Blender's
    # bottom-up rows, so the whole glare lands one row off.
    frame, psf = _frame(), _psf(21)
    expected = _render(frame, psf)
    even = np.pad(
        np.asarray(blender_kernel(psf)), ((1, 0), (1, 0), (0, 0))
    )  # centre at 11 = 22 // 2
    got = blender_convolve(frame, even, normalize=False)
    assert _max_err(got, expected) > 100 * RTOL * expected.max()
    shifted = np.roll(expected, -1, axis=0)  # one row up
    assert _max_err(got[:-1], shifted[:-1]) <= RTOL * expected.max()
    with pytest.raises(ConfigError, match="odd"):
        blender_kernel(psf, 22)


def test_blender_normalisation_removes_the_tint_and_tint_restores_it():
    frame, psf = _frame(), _psf()
    kernel = np.asarray(blender_kernel(psf))
    energy = np.asarray(channel_energy(kernel), np.float64)
    np.testing.assert_allclose(energy, [0.9, 0.8, 0.7], rtol=1e-5)
    normalised = blender_convolve(frame, kernel, normalize=True)
    # Each channel now carries unit energy: the PSF's own colour (0.9 : 0.8 : 0.7) is gone.
    neutral = _render(frame, psf / energy.astype(np.float32))
    assert _max_err(normalised, neutral) <= RTOL * neutral.max()
    expected = _render(frame, psf)
    assert _max_err(normalised, expected) > 0.05 * expected.max()
    assert _max_err(normalised * energy, expected) <= RTOL * expected.max()


def test_blender_glare_node_with_tint_gives_invglare_render():
    frame, psf = _frame(), _psf()
    kernel = np.asarray(blender_kernel(psf))
    tint = np.asarray(channel_energy(kernel))
    glare, image = blender_glare_output(frame, kernel, threshold=0.0, strength=1.0, tint=tint)
    expected = _render(frame, psf)
    assert _max_err(glare, expected) <= RTOL * expected.max()
    # The Image output is the frame plus the glare: the unscattered light counted twice.
    assert _max_err(image, frame + expected) <= RTOL * expected.max()


def test_blender_mono_psf_gives_three_equal_channels():
    frame = _frame()
    mono = _psf()[..., 1]
    kernel = np.asarray(blender_kernel(mono))
    assert kernel.shape == (21, 21, 3)
    np.testing.assert_array_equal(kernel[..., 0], kernel[..., 2])
    expected = _render(frame, np.repeat(mono[..., None], 3, axis=-1))
    got = blender_convolve(frame, kernel, normalize=False)
    assert _max_err(got, expected) <= RTOL * expected.max()


# ------------------------------------------------------------------ Unreal


def test_unreal_bloom_is_invglare_render_over_the_kernel_energy():
    frame, psf = _frame(), _psf()
    texture = np.asarray(unreal_kernel(psf))
    viewport = (52, 40)
    size = unreal_convolution_scale(texture.shape[0], viewport)
    assert size == pytest.approx(21 / 40)
    bloom = unreal_bloom(frame, texture, size, viewport)
    energy = np.asarray(channel_energy(texture), np.float64)
    expected = _render(frame, psf)
    # The engine takes the kernel's total as all of the light; Intensity = energy restores it.
    assert _max_err(bloom * energy, expected) <= RTOL * expected.max()


def test_unreal_kernel_keeps_the_unclipped_centre_and_core_to_halo_ratio():
    psf = _psf()
    texture = np.asarray(unreal_kernel(psf, 31))
    c = 31 // 2
    assert peak_offset_px(texture) == (0, 0)
    np.testing.assert_array_equal(texture[c, c], psf[10, 10])  # not clipped, not rescaled
    fraction = np.asarray(centre_fraction(texture))
    exact = psf[10, 10].astype(np.float64) / psf.astype(np.float64).sum(axis=(0, 1))
    # rtol: the kernel's total is a float32 sum of 31 x 31 pixels, whose rounding follows the
    # order XLA sums in (it moved by 1.6e-6 after another test in the same process).
    np.testing.assert_allclose(fraction, exact, rtol=1e-5)
    assert np.all((fraction > 0.05) & (fraction < 0.5))


def test_unreal_layout_spreads_asymmetric_psfs_the_right_way():
    frame, psf = _frame(), _psf()
    reflected = np.asarray(blender_kernel(psf))  # the Blender layout, wrong for a spread
    bloom = unreal_bloom(frame, reflected, 21 / 40, (52, 40))
    expected = _render(frame, psf) / np.asarray(channel_energy(reflected), np.float64)
    assert _max_err(bloom, expected) > 100 * RTOL * expected.max()


# ------------------------------------------------------------ the files, as the tools load them


@pytest.mark.parametrize("target", TARGETS)
def test_exported_exr_loads_as_the_tools_read_it(tmp_path, target):
    psf = _psf()
    kernel = np.asarray(kernel_for(target, psf, 25))
    path = write_exr(tmp_path / f"{target}.exr", kernel, pixel_scale_deg=0.01)
    with OpenEXR.File(str(path), separate_channels=True) as exr:
        channels = exr.channels()
        assert sorted(channels) == ["B", "G", "R"]
        assert all(ch.pixels.dtype == np.float32 for ch in channels.values())
        loaded = np.stack([channels[c].pixels for c in "RGB"], axis=-1)
    assert loaded.shape == (25, 25, 3) and loaded.shape[0] % 2 == 1
    np.testing.assert_array_equal(loaded, kernel)  # float32 round trip is exact
    # Unreal: brightest texel at UV (0.5, 0.5); Blender's centre row is the middle one in
    # both row orders; both: the energy is the PSF's, each tool's normalisation is 1 / it.
    assert peak_offset_px(loaded) == (0, 0)
    assert loaded[::-1].argmax() == loaded.argmax() or target == "unreal"
    np.testing.assert_allclose(loaded.sum(axis=(0, 1)), [0.9, 0.8, 0.7], rtol=1e-5)
    frame = _frame()
    expected = _render(frame, psf)
    if target == "blender":
        got = blender_convolve(frame, loaded, normalize=False)
    else:
        got = unreal_bloom(frame, loaded, 25 / 40, (52, 40)) * loaded.sum(axis=(0, 1))
    assert _max_err(got, expected) <= RTOL * expected.max()


# ------------------------------------------------------------------ the pieces


def test_centred_crops_and_pads_about_the_centre():
    psf = np.zeros((6, 8), np.float32)
    psf[3, 4] = 1.0  # the centre (h // 2, w // 2)
    psf[0, 0] = 0.5
    padded = np.asarray(centred(psf, 11))
    assert padded[5, 5] == 1.0 and padded[2, 1] == 0.5 and padded.sum() == 1.5
    cropped = np.asarray(centred(psf, 3))
    assert cropped.shape == (3, 3) and cropped[1, 1] == 1.0 and cropped.sum() == 1.0


def test_rgb_and_energy_helpers():
    mono = np.full((3, 3), 1.0 / 9, np.float32)
    three = np.asarray(rgb(mono))
    assert three.shape == (3, 3, 3)
    assert float(luminance_energy(three)) == pytest.approx(1.0, rel=1e-6)
    with pytest.raises(InputDataError, match="shape"):
        rgb(np.ones((3, 3, 2)))


def test_kernels_work_under_jit():
    psf = jnp.asarray(_psf())
    eager = blender_kernel(psf, 25)
    jitted = jax.jit(lambda p: blender_kernel(p, 25))(psf)
    np.testing.assert_array_equal(np.asarray(eager), np.asarray(jitted))


def test_viewport_pixel_scale_is_the_pinhole_centre_pixel():
    # f = (W / 2) / tan(fov / 2) pixels; at 90 deg, f = W / 2 and one pixel is 2 / W rad.
    assert viewport_pixel_scale_deg(90.0, 1920) == pytest.approx(math.degrees(2 / 1920), rel=1e-12)
    # A narrow field is nearly linear: fov / W.
    assert viewport_pixel_scale_deg(1.0, 1000) == pytest.approx(1e-3, rel=1e-4)
    with pytest.raises(PhysicsRangeError, match="field of view"):
        viewport_pixel_scale_deg(180.0, 100)
    with pytest.raises(PhysicsRangeError, match="width"):
        viewport_pixel_scale_deg(40.0, 0)


@pytest.mark.parametrize(
    ("target", "npix", "match"),
    [
        ("maya", None, "unknown kernel target 'maya'; choose one of blender, unreal"),
        ("blender", 64, "must be odd, got 64"),
        ("unreal", 1, "odd integer >= 3, got 1"),
        ("unreal", 65.0, "odd integer >= 3, got 65.0"),
        ("blender", True, "odd integer >= 3"),
    ],
)
def test_bad_requests_are_refused(target, npix, match):
    with pytest.raises(ConfigError, match=match):
        check_kernel_request(target, npix)


def test_requests_are_case_insensitive():
    assert check_kernel_request("Unreal", 5) == "unreal"
    with pytest.raises(ConfigError, match="viewport"):
        unreal_convolution_scale(5, (0, 10))
