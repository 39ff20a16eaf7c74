"""The holographic eye's base layer and depth layers against eq. 2.2 and closed forms."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
import pytest
from helpers import x64

from invglare.errors import PhysicsRangeError
from invglare.optics.holographic import (
    HoloSampling,
    depth_layers_needed,
    fresnel_base_field,
    layer_vergences,
    spherical_wave_sum,
    vergence_step_per_mm,
)

LAM_NM = 500.0


def _sources_on_bins(sampling, bins, depths_mm, amps):
    """Bins (signed ky, kx) with their depths: the FFT-order amplitudes of the fast path
    (each carrying its exact phase exp(i k R) / R) and the positions for eq. 2.2."""
    n = sampling.npix
    pitch = sampling.pitch_mm(LAM_NM)
    k = 2 * math.pi / (LAM_NM * 1e-6)
    per_layer = {}
    positions = []
    for (ky, kx), z, a in zip(bins, depths_mm, amps, strict=True):
        # Bin k is the plane wave exp(i 2 pi k x / (n pitch)): it travels along +lambda f,
        # so its source lies in the direction tan = -lambda f.
        ty, tx = -LAM_NM * 1e-6 * ky / (n * pitch), -LAM_NM * 1e-6 * kx / (n * pitch)
        p = np.array([z * tx, z * ty, z])
        r = np.linalg.norm(p)
        layer = per_layer.setdefault(z, np.zeros((n, n), complex))
        layer[ky % n, kx % n] += a * np.exp(1j * k * r) / r
        positions.append(p)
    vergences = [1.0 / z for z in per_layer]
    return np.stack(list(per_layer.values())), np.asarray(vergences), np.asarray(positions)


def test_fast_base_layer_equals_spherical_wave_sum_32px():
    # 32^2 grid, 5 mm window at 500 nm, 25 sources on the central 5 x 5 bins at 10 m. The
    # fast path's approximations (base_layer docstring) are all below 1e-6 rad here:
    # k a t^3 / 2 = 4e-8, k a^2 u^2 / (2 R) = 2e-8, k a^4 / (8 R^3) = 1e-8; the curvature
    # itself is k a^2 / (2 z) = 2 rad, so it is tested.
    with x64():
        s = HoloSampling(32, 1e-4, (LAM_NM,))
        rng = np.random.default_rng(0)
        bins = [(ky, kx) for ky in range(-2, 3) for kx in range(-2, 3)]
        amps = rng.standard_normal(25) + 1j * rng.standard_normal(25)
        layers, v, pos = _sources_on_bins(s, bins, [1e4] * 25, amps)
        fast = fresnel_base_field(jnp.asarray(layers), jnp.asarray(v), s.grid(LAM_NM), LAM_NM)
        ref = jnp.fft.ifftshift(spherical_wave_sum(jnp.asarray(amps), pos, s.grid(LAM_NM), LAM_NM))
        rel = float(jnp.max(jnp.abs(fast - ref)) / jnp.max(jnp.abs(ref)))
    assert rel < 1e-4, rel


def test_fast_base_layer_with_two_depth_layers_equals_spherical_wave_sum():
    # Two depths (8 m and 12 m): one inverse FFT and one curvature each, exact per layer.
    with x64():
        s = HoloSampling(32, 1e-4, (LAM_NM,))
        rng = np.random.default_rng(1)
        bins = [(ky, kx) for ky in range(-2, 3) for kx in range(-2, 3)]
        depths = [8e3 if (ky + kx) % 2 else 1.2e4 for ky, kx in bins]
        amps = rng.standard_normal(25) + 1j * rng.standard_normal(25)
        layers, v, pos = _sources_on_bins(s, bins, depths, amps)
        fast = fresnel_base_field(jnp.asarray(layers), jnp.asarray(v), s.grid(LAM_NM), LAM_NM)
        ref = jnp.fft.ifftshift(spherical_wave_sum(jnp.asarray(amps), pos, s.grid(LAM_NM), LAM_NM))
        rel = float(jnp.max(jnp.abs(fast - ref)) / jnp.max(jnp.abs(ref)))
    assert rel < 1e-4, rel


def test_fast_base_layer_error_follows_the_paraxial_bound():
    # Near (300 mm) and oblique (up to 16 bins = 1.6e-3 rad): the error is the paraxial one
    # of the docstring, dominated by the oblique curvature k a^2 u^2 / (2 R) and the cubic
    # term; it stays within their sum and is not negligible (the bound is not vacuous).
    with x64():
        s = HoloSampling(32, 1e-4, (LAM_NM,))
        bins = [(0, 15), (15, 0), (-15, -15), (10, -12)]
        amps = np.ones(4, complex)
        z = 300.0
        layers, v, pos = _sources_on_bins(s, bins, [z] * 4, amps)
        g = s.grid(LAM_NM)
        fast = fresnel_base_field(jnp.asarray(layers), jnp.asarray(v), g, LAM_NM)
        ref = jnp.fft.ifftshift(spherical_wave_sum(jnp.asarray(amps), pos, g, LAM_NM))
        # Amplitude per source is 1 / R ~ 1 / z; the phase error of each adds up.
        err = float(jnp.max(jnp.abs(fast - ref))) * z
    k = 2 * math.pi / (LAM_NM * 1e-6)
    a = math.sqrt(2) * s.window_mm(LAM_NM) / 2  # the window's corner
    t = math.hypot(15, 15) * 1e-4
    bound = k * (a**2 * t**2 / (2 * z) + a**3 * t / (2 * z**2) + a * t**3 / 2 + a**4 / (8 * z**3))
    assert 0.02 * 4 * bound < err < 4 * bound, (err, bound)


def test_spherical_wave_sum_of_one_axial_source_is_the_spherical_wave():
    with x64():
        s = HoloSampling(16, 1e-4, (LAM_NM,))
        g = s.grid(LAM_NM)
        u = spherical_wave_sum(jnp.ones(1), jnp.asarray([[0.0, 0.0, 500.0]]), g, LAM_NM, chunk=1)
        y, x = g.mesh_mm()
        r = jnp.sqrt(x * x + y * y + 500.0**2)
        k = 2 * math.pi / (LAM_NM * 1e-6)
        np.testing.assert_allclose(np.asarray(u), np.asarray(jnp.exp(1j * k * r) / r), rtol=1e-12)


# ---------------------------------------------------------------------- depth layers


def test_depth_layers_needed_closed_form():
    # (1/500 mm - 0) * (1.5 mm)^2 / 460 nm = 9.78 -> 10 layers (quarter-wave rounding).
    assert depth_layers_needed(500.0, math.inf, 3.0, 460.0) == 10
    assert depth_layers_needed(500.0, 1000.0, 3.0, 460.0) == 5
    assert depth_layers_needed(2000.0, 2000.0, 6.0, 550.0) == 1
    assert vergence_step_per_mm(3.0, 460.0) == pytest.approx(460e-6 / 1.5**2)
    with pytest.raises(PhysicsRangeError, match="near <= far"):
        depth_layers_needed(1000.0, 500.0, 3.0, 550.0)


@pytest.mark.parametrize("near_mm, far_mm, pupil_mm", [(400.0, 5000.0, 3.0), (250.0, 1e9, 4.0)])
def test_layer_count_keeps_rounding_within_a_quarter_wave(near_mm, far_mm, pupil_mm):
    lam = 460.0
    n = depth_layers_needed(near_mm, far_mm, pupil_mm, lam)
    v = 1.0 / np.geomspace(near_mm, far_mm, 4001)
    vergence = jnp.asarray(v.reshape(1, -1))
    a = pupil_mm / 2

    def worst_opd_waves(layers):
        centres, index = layer_vergences(vergence, jnp.ones_like(vergence), layers)
        err = np.abs(v - np.asarray(centres)[np.asarray(index)[0]])
        return float(err.max()) * a * a / 2 / (lam * 1e-6)

    assert worst_opd_waves(n) <= 0.25 + 1e-9
    if n > 1:
        assert worst_opd_waves(n - 1) > 0.25


def test_layer_vergences_one_layer_and_empty_bins():
    v = jnp.asarray([[1e-3, 2e-3], [5.0, 3e-3]])
    w = jnp.asarray([[1.0, 1.0], [0.0, 1.0]])  # the 5.0 has no light: it must not count
    centres, index = layer_vergences(v, w, 2)
    np.testing.assert_allclose(np.asarray(centres), [1.5e-3, 2.5e-3], rtol=1e-6)
    assert np.asarray(index).tolist() == [[0, 1], [1, 1]]
    one, _ = layer_vergences(v, w, 1)
    np.testing.assert_allclose(np.asarray(one), [2e-3], rtol=1e-6)
