"""The holographic stack: speckle against iterations, and the speckle-free limit."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from invglare.aperture.eye import Pupil
from invglare.errors import ConfigError
from invglare.optics.holographic import (
    ChannelStack,
    HoloSampling,
    image_to_bins,
    iterate_intensity,
    point_response,
    propagation_kernel,
    random_phasors,
    speckle_contrast,
    speckle_free,
    stack_field,
)
from invglare.optics.holographic import stack as stack_module
from invglare.optics.holographic.stack import tile_weights

LAM_NM = 550.0
N = 64


def _stack(mask_in_front: bool, pupil_mm: float = 2.5):
    """A one-channel stack on a 64^2 grid (8 mm window): a 2.5 mm pupil, and optionally a
    random amplitude screen 60 mm in front of it (a stand-in for lashes, cheap to build;
    far enough that the light of the grid's outer directions crosses it a pixel away)."""
    s = HoloSampling.from_window(N, 8.0, (LAM_NM,))
    g = s.grid(LAM_NM)
    pupil = Pupil(pupil_mm).coverage(g)
    gain = 1.0 / jnp.mean(pupil)
    if not mask_in_front:
        return ChannelStack(pupil.astype(jnp.complex64)[None], (), (), gain)
    rng = np.random.default_rng(5)
    screen = (rng.random((N, N)) > 0.5).astype(np.complex64)
    return ChannelStack(
        jnp.asarray(screen)[None],
        (propagation_kernel(g, LAM_NM, 60.0).astype(jnp.complex64),),
        (pupil.astype(jnp.complex64),),
        gain,
    )


def _batch(stack):
    return jax.tree.map(lambda x: x[None], stack)


@pytest.mark.parametrize("whole", [True, False], ids=["whole-fft", "pruned-fft"])
@pytest.mark.parametrize("m", [64, 40, 39])
def test_stack_field_is_the_field_of_the_written_out_stack(m, whole, monkeypatch):
    # The stack's field, written out with numpy in FFT layout: the whole inverse FFT of the
    # bins, its centred m x m crop times the front, one angular-spectrum step and a
    # transmission, zero-padded back to N around the centre and transformed to the retina.
    # Checks the centring ramp (phase included) for the whole grid, an even and an odd crop,
    # with the base layer's window from a whole and from a pruned inverse FFT.
    monkeypatch.setattr(stack_module, "WHOLE_FFT_MAX_NPIX", N if whole else 0)
    rng = np.random.default_rng(11)

    def cplx(*shape):
        return (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)).astype(np.complex128)

    bins, front, trans = cplx(N, N), cplx(m, m), cplx(m, m)
    kernel = np.exp(1j * rng.uniform(0, 2 * np.pi, (m, m)))
    lo = N // 2 - m // 2
    window = np.fft.fftshift(np.fft.ifft2(bins, norm="ortho"))[lo : lo + m, lo : lo + m]
    u = np.fft.ifft2(np.fft.fft2(window * front) * kernel) * trans
    padded = np.zeros((N, N), complex)
    padded[lo : lo + m, lo : lo + m] = u
    want = np.fft.fft2(np.fft.ifftshift(padded), norm="ortho")
    with jax.enable_x64(True):
        stack = ChannelStack(
            jnp.asarray(front)[None], (jnp.asarray(kernel),), (jnp.asarray(trans),),
            jnp.ones(()), N,
        )  # fmt: skip
        got = np.asarray(stack_field(jnp.asarray(bins), stack))
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.abs(want).max())


def test_speckle_contrast_falls_as_one_over_sqrt_n():
    # A uniform frame through a pupil: one draw is fully developed speckle (contrast ~1), the
    # average of n independent draws has contrast 1 / sqrt(n). The speckle-free limit is
    # uniform (periodic grid), so the contrast is all speckle.
    stack = _batch(_stack(False))
    amps = jnp.ones((1, N, N))
    key = jax.random.key(3)
    c = {}
    for n in (1, 4, 16, 64):
        img = iterate_intensity(amps, stack, key, n)[0]
        c[n] = float(speckle_contrast(img))
    assert c[1] == pytest.approx(1.0, abs=0.12)
    for n in (4, 16, 64):
        assert c[n] * np.sqrt(n) == pytest.approx(c[1], rel=0.2), c


def test_quaternary_phases_give_the_same_speckle_as_uniform_ones():
    stack = _batch(_stack(False))
    amps = jnp.ones((1, N, N))
    for kind in ("uniform", "quaternary"):
        one = iterate_intensity(amps, stack, jax.random.key(8), 1, phases=kind)[0]
        many = iterate_intensity(amps, stack, jax.random.key(8), 16, phases=kind)[0]
        assert float(speckle_contrast(one)) == pytest.approx(1.0, abs=0.12)
        assert float(speckle_contrast(many)) * 4 == pytest.approx(1.0, rel=0.2)
    ph = np.asarray(random_phasors(jax.random.key(0), (4096,), "quaternary"))
    assert set(np.round(ph, 6)) <= {1, 1j, -1, -1j}
    assert abs(np.mean(ph)) < 0.05 and abs(np.mean(ph**2)) < 0.05


def _frame_bins(seed=0):
    rng = np.random.default_rng(seed)
    frame = np.zeros((N, N))
    frame[20:44, 16:40] = 1.0 + rng.random((24, 24))
    frame[10, 50] = 300.0  # a bright point off the axis
    return jnp.asarray(image_to_bins(jnp.asarray(frame)))[None]


def test_iteration_average_converges_to_the_speckle_free_limit():
    # Shift-invariant stack (the pupil only): the limit is exact, and the average of n draws
    # approaches it as 1 / sqrt(n).
    stack = _batch(_stack(False))
    inten = _frame_bins()
    limit = speckle_free(inten, stack)[0]
    # A circular convolution keeps the product of the sums.
    psf_energy = float(point_response(_stack(False), (0, 0)).sum())
    assert float(limit.sum()) == pytest.approx(float(inten.sum()) * psf_energy, rel=1e-5)
    amps = jnp.sqrt(inten)

    def err(n, seed):
        img = iterate_intensity(amps, stack, jax.random.key(seed), n)[0]
        return float(jnp.linalg.norm(img - limit) / jnp.linalg.norm(limit))

    e4 = np.mean([err(4, s) for s in range(3)])
    e64 = np.mean([err(64, s) for s in range(3)])
    assert e64 < 0.2
    assert e4 / e64 == pytest.approx(4.0, rel=0.25)


def test_limit_of_a_stack_with_a_screen_in_front_is_the_sum_of_point_responses():
    # With an amplitude screen in front of the pupil the PSF changes with direction. The
    # expectation over phases is still sum_j |C_j|^2 |h_j|^2 (each source its own PSF): the
    # iteration average converges to it, and the one-PSF (tiles = 1) limit does not.
    stack = _stack(True)
    rng = np.random.default_rng(2)
    inten = np.zeros((N, N))
    # Four sources near the grid's corners (their light crosses the screen a pixel away from
    # the on-axis light) and one on the axis.
    where = [(28, 28), (N - 28, 28), (28, N - 28), (N - 28, N - 28), (0, 0)]
    for ky, kx in where:
        inten[ky, kx] = 1.0 + rng.random()
    exact = sum(
        inten[ky, kx] * jnp.roll(point_response(stack, (ky, kx)), (ky, kx), axis=(0, 1))
        for ky, kx in where
    )
    amps = jnp.sqrt(jnp.asarray(inten))[None]
    avg = iterate_intensity(amps, _batch(stack), jax.random.key(1), 512)[0]
    one_psf = speckle_free(jnp.asarray(inten)[None], _batch(stack))[0]
    err_avg = float(jnp.linalg.norm(avg - exact) / jnp.linalg.norm(exact))
    err_one = float(jnp.linalg.norm(one_psf - exact) / jnp.linalg.norm(exact))
    # Five sources, 256 draws: the relative error of the average is about sqrt(5 / 256) of
    # the speckle's own contrast; the single PSF misses the direction dependence.
    assert err_avg < 0.2
    assert err_one > 3 * err_avg, (err_one, err_avg)  # measured 0.057 and 0.012


def test_tiled_limit_is_exact_at_the_tile_centres():
    # A source at a tile centre gets that tile's exact PSF (its weight there is 1).
    stack = _stack(True)
    tiles = 4
    centre = (int(N / tiles * 0.5), int(N / tiles * 2.5))  # image (row, col) of a tile centre
    img = np.zeros((N, N))
    img[centre] = 1.0
    bins = jnp.asarray(image_to_bins(jnp.asarray(img)))
    ky, kx = (int(v[0]) for v in np.nonzero(np.asarray(bins)))
    exact = jnp.roll(point_response(stack, (ky, kx)), (ky, kx), axis=(0, 1))
    tiled = speckle_free(
        bins[None], _batch(stack), tiles=tiles, to_bins=lambda x: np.asarray(image_to_bins(x))
    )[0]
    np.testing.assert_allclose(np.asarray(tiled), np.asarray(exact), atol=1e-6 * float(exact.max()))


def test_tile_weights_are_a_partition_of_unity():
    w = tile_weights(64, 4, 8, 56)
    np.testing.assert_allclose(w.sum(axis=0), 1.0)
    assert w.shape == (4, 64) and w.min() >= 0
    assert w[0, :14].min() == 1.0 and w[-1, 50:].min() == 1.0
    with pytest.raises(ConfigError, match="tiles"):
        tile_weights(64, 0)


def test_draws_do_not_depend_on_the_chunk_and_iterations_are_checked():
    stack = _batch(_stack(False))
    amps = jnp.sqrt(_frame_bins())
    a = iterate_intensity(amps, stack, jax.random.key(4), 6, chunk=1)
    b = iterate_intensity(amps, stack, jax.random.key(4), 6, chunk=4)  # 2 chunks of 3
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=2e-5, atol=1e-6)
    for bad in (0, -1, 2.5):
        with pytest.raises(ConfigError, match="iterations"):
            iterate_intensity(amps, stack, jax.random.key(4), bad)


def test_stack_is_jittable_and_vmappable_over_keys():
    stack = _batch(_stack(True))
    amps = jnp.sqrt(_frame_bins())
    keys = jax.random.split(jax.random.key(0), 3)
    run = jax.jit(lambda k: iterate_intensity(amps, stack, k, 2))
    batched = jax.vmap(run)(keys)
    for i in range(3):
        np.testing.assert_allclose(
            np.asarray(batched[i]), np.asarray(run(keys[i])), rtol=1e-4, atol=1e-6
        )


def test_layer_index_is_required_with_several_layers():
    stack = _stack(False)
    two = ChannelStack(jnp.concatenate([stack.front, stack.front]), (), (), stack.gain)
    with pytest.raises(ConfigError, match="layer_index"):
        stack_field(jnp.ones((N, N), jnp.complex64), two)
