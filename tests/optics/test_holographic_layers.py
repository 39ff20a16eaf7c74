"""Thin layers of the holographic eye: propagation kernels, Parseval, tear film, spectacles."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.special
from helpers import x64

from invglare._core.grids import ApertureGrid
from invglare.aperture.eye import Pupil
from invglare.errors import ConfigError, PhysicsRangeError
from invglare.optics.fresnel import angular_spectrum
from invglare.optics.holographic import (
    ChannelStack,
    HoloSampling,
    Spectacles,
    TearFilm,
    point_response,
    propagate_periodic,
    propagation_kernel,
    spectacle_phase,
    thin_lens_phase,
    vergence_chirp,
)

LAM_NM = 550.0


def _random_field(n, seed=0):
    rng = np.random.default_rng(seed)
    return jnp.asarray(rng.standard_normal((n, n)) + 1j * rng.standard_normal((n, n)))


def test_kernel_propagation_equals_invglare_angular_spectrum():
    # The precomputed kernel is angular_spectrum's own (same transfer function and band
    # limit), on the periodic grid (pad_npix = n) and padded alike.
    with x64():
        grid = ApertureGrid(64, 0.05)
        field = _random_field(64)
        for pad in (64, 128):
            ref = angular_spectrum(field, grid, LAM_NM, 12.0, pad_npix=pad)
            k = propagation_kernel(grid, LAM_NM, 12.0, pad_npix=pad)
            lo = (pad - 64) // 2
            ours = propagate_periodic(jnp.pad(field, lo), k)[lo : lo + 64, lo : lo + 64]
            np.testing.assert_allclose(np.asarray(ours), np.asarray(ref), atol=1e-12)


def test_band_limit_of_a_far_plane_keeps_only_a_narrow_cone():
    # Why depth planes metres away are not propagated by the angular spectrum: over 2 m on an
    # 8 mm window the band limit keeps |f| <= 1 / (lambda sqrt((2 z / W)^2 + 1)), directions
    # within W / (2 z) = 2e-3 rad of the axis.
    grid = ApertureGrid(512, 8.0 / 512)
    k = propagation_kernel(grid, LAM_NM, 2000.0)
    freqs = np.fft.fftfreq(512, 8.0 / 512)
    kept = freqs[np.abs(np.asarray(k[0])) > 0]
    assert np.max(np.abs(kept)) * LAM_NM * 1e-6 == pytest.approx(8.0 / (2 * 2000.0), rel=0.02)


def test_phase_only_layers_and_propagation_conserve_energy():
    # Parseval: a field through lens, spectacles, tear film and curvature phases and three
    # angular-spectrum steps (whose band limit does not cut into this grid's band) keeps its
    # energy to round-off.
    with x64():
        s = HoloSampling.from_window(64, 8.0, (LAM_NM,))
        g = s.grid(LAM_NM)
        film = TearFilm(0.2, 0.8, key=1, pattern="random")
        u = _random_field(64, 2)
        e0 = float(jnp.sum(jnp.abs(u) ** 2))
        layers = [
            vergence_chirp(g, LAM_NM, 1 / 800.0),
            spectacle_phase(g, LAM_NM, -1.5, 0.75, 30.0),
            film.transmission(g, LAM_NM),
            thin_lens_phase(g, LAM_NM, 2e-3),
        ]
        for t in layers:
            np.testing.assert_allclose(np.abs(np.asarray(t)), 1.0, atol=1e-12)
            u = propagate_periodic(u * t, propagation_kernel(g, LAM_NM, 4.0))
        e1 = float(jnp.sum(jnp.abs(u) ** 2))
    assert e1 == pytest.approx(e0, rel=1e-12)


def _clear_stack(front, kernels=(), transmissions=()):
    """A one-layer stack of centred planes (as the model builds them)."""
    return ChannelStack(front[None], tuple(kernels), tuple(transmissions), jnp.ones(()))


def test_sinusoidal_tear_film_zero_order_is_bessel_closed_form():
    # d = A sin(2 pi u / L) sin(2 pi v / L) is the phase grating exp(i m sin a sin b) with
    # m = k (eta - 1) A; its undiffracted (zero-order) power is J0(m / 2)^4 (the average
    # over b of J0(m sin b) is J0(m / 2)^2). The period divides the window, so every order
    # falls on a bin; 3.6 mm of propagation changes no order's power.
    with x64():
        s = HoloSampling.from_window(64, 8.0, (LAM_NM,))
        g = s.grid(LAM_NM)
        amp_um = 0.35
        # 16 samples per period: the sampled grating's zero order is the average over the
        # samples, which converges exponentially (8 samples would err by 3e-6).
        film = TearFilm(amp_um, 8.0 / 4, pattern="sinusoid")
        stack = _clear_stack(
            film.transmission(g, LAM_NM),
            [propagation_kernel(g, LAM_NM, 3.6)],
            [jnp.ones((64, 64), complex)],
        )
        psf = np.asarray(point_response(stack, (0, 0)))
    m = 2 * math.pi / (LAM_NM * 1e-6) * (film.refractive_index - 1) * amp_um * 1e-3
    assert psf.sum() == pytest.approx(1.0, rel=1e-10)
    assert psf[0, 0] == pytest.approx(scipy.special.j0(m / 2) ** 4, rel=1e-9)
    # The first orders sit at (+-4, +-4) bins (the sum and difference waves of the product).
    assert psf[4, 4] > 0.01 and psf[4, 0] < 1e-20


def test_random_tear_film_has_the_rms_and_slope_it_is_given():
    # Over a window of 40 correlation lengths the spatial rms is the amplitude and the rms
    # slope sqrt(2) A / l (one draw of 64 modes: within 12 %).
    grid = ApertureGrid(256, 20.0 / 256)
    film = TearFilm(0.15, 0.5, key=4, pattern="random")
    d = np.asarray(film.height_mm(grid)) - 7e-3  # minus the mean thickness
    assert np.sqrt(np.mean(d**2)) * 1e3 == pytest.approx(0.15, rel=0.12)
    slope = np.asarray(film.slope(grid))
    assert np.sqrt(np.mean(slope**2)) == pytest.approx(math.sqrt(2) * 0.15e-3 / 0.5, rel=0.12)
    # The closed-form slope is the derivative of the height (central differences).
    gy, gx = np.gradient(d, 20.0 / 256)
    inner = (slice(8, -8), slice(8, -8))
    np.testing.assert_allclose(
        np.hypot(gx, gy)[inner], slope[inner], atol=0.03 * float(slope.max())
    )


def test_tear_film_that_aliases_is_refused_with_the_pitch_it_needs():
    grid = ApertureGrid(64, 8.0 / 64)  # 125 um pitch
    # rms slope sqrt(2) 1 um / 0.1 mm = 0.014; (eta - 1) slope = 5e-3 rad per ... >> the grid's
    film = TearFilm(1.0, 0.1, key=0, pattern="random")
    with pytest.raises(PhysicsRangeError, match=r"aliases its angular spectrum.*pitch <="):
        film.check_sampled(grid, LAM_NM)
    TearFilm(0.01, 2.0, key=0, pattern="random").check_sampled(grid, LAM_NM)


def test_animated_tear_film_breaks_up_after_the_breakup_time():
    grid = ApertureGrid(128, 8.0 / 128)
    film = TearFilm(
        0.05, 0.6, key=2, pattern="random", breakup_time_s=8.0, breakup_spots=3,
        breakup_growth_mm_per_s=0.3, breakup_edge_mm=0.4, thinning_um_per_s=0.2,
        irregularity_growth_per_s=0.1,
    )  # fmt: skip
    early = np.asarray(film.height_mm(grid, 5.0))
    late = np.asarray(film.height_mm(grid, 14.0))
    assert early.min() > 4e-3  # 7 um thinned by 1 um, no spot yet
    dry = late < 1e-7
    assert dry.sum() > 30  # the spots have opened
    later = np.asarray(film.height_mm(grid, 16.0))
    assert (later < 1e-7).sum() > dry.sum()  # and keep growing
    # Irregularities grow as (1 + g t) about the thinning mean (the same film without spots).
    no_spots = TearFilm(
        0.05, 0.6, key=2, pattern="random", thinning_um_per_s=0.2, irregularity_growth_per_s=0.1
    )
    a, b = (np.asarray(no_spots.height_mm(grid, t)) for t in (5.0, 16.0))
    assert np.mean(b) == pytest.approx(np.mean(a) - 2.2e-3, abs=2e-5)  # 0.2 um/s over 11 s
    assert np.std(b) / np.std(a) == pytest.approx((1 + 1.6) / (1 + 0.5), rel=1e-4)


def test_tear_film_rejects_bad_parameters():
    with pytest.raises(ConfigError, match="pattern"):
        TearFilm(0.1, 0.5, pattern="waves")
    with pytest.raises(PhysicsRangeError, match="scale_mm"):
        TearFilm(0.1, 0.0)
    with pytest.raises(PhysicsRangeError, match="amplitude_um"):
        TearFilm(-0.1, 0.5)


def test_spectacle_sphere_is_a_source_at_its_far_point():
    # A -2 D lens 15.6 mm in front of the pupil makes light from infinity diverge from its
    # focal point 500 mm in front of the lens: the field in a 2 mm pupil equals that of a
    # source 515.6 mm away (angular spectrum over 15.6 mm against the Fresnel curvature).
    # The grid's half field (0.012 rad) holds the lens's bending (2e-3 rad/mm) out to the
    # window's edge; the light walks 0.1 mm on the way.
    with x64():
        s = HoloSampling.from_window(256, 6.0, (LAM_NM,))
        g = s.grid(LAM_NM)
        pupil = Pupil(2.0).coverage(g).astype(complex)
        through = _clear_stack(
            Spectacles(-2.0).transmission(g, LAM_NM),
            [propagation_kernel(g, LAM_NM, 15.6)],
            [pupil],
        )
        direct = _clear_stack(vergence_chirp(g, LAM_NM, 1 / 515.6) * pupil)
        a, b = point_response(through, (0, 0)), point_response(direct, (0, 0))
        # A spherical wave's amplitude falls as 1 / r: from 500 to 515.6 mm.
        b = b * (500.0 / 515.6) ** 2
        # Measured: 2.5e-5 of the peak (the Fresnel curvature against the exact kernel).
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-4 * float(b.max()))


def test_cylinder_axis_rotates_the_psf():
    # A cylinder's power acts across its axis: a 90-degree axis gives the transposed PSF,
    # and the blur lies across the axis (the PSF is long in y for an axis along x).
    s = HoloSampling.from_window(64, 6.0, (LAM_NM,))
    g = s.grid(LAM_NM)
    opening = (jnp.hypot(*g.mesh_mm()) < 2.0).astype(complex)

    def psf(axis_deg):
        t = Spectacles(0.0, 3.0, axis_deg).transmission(g, LAM_NM) * opening
        return np.fft.fftshift(np.asarray(point_response(_clear_stack(t), (0, 0))))

    p0, p90 = psf(0.0), psf(90.0)
    np.testing.assert_allclose(p90, p0.T, atol=1e-6 * p0.max())
    yy, xx = np.mgrid[:64, :64] - 32
    var_y, var_x = (p0 * yy**2).sum() / p0.sum(), (p0 * xx**2).sum() / p0.sum()
    assert var_y > 5 * var_x


def test_vergence_chirp_is_jittable_and_vmappable_over_wavelengths():
    s = HoloSampling.from_window(32, 6.0, (640.0, 550.0, 460.0))
    lams = jnp.asarray(s.wavelengths_nm)

    def one(lam):
        g = ApertureGrid(32, lam * 1e-6 / (32 * s.pixel_scale_rad))
        return vergence_chirp(g, lam, 1e-3)

    batched = jax.jit(jax.vmap(one))(lams)
    for i, lam in enumerate(s.wavelengths_nm):
        np.testing.assert_allclose(np.asarray(batched[i]), np.asarray(one(lam)), atol=1e-5)
