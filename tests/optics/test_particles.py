"""Wide-angle scatter of small particles in closed form (issue 27, item 3)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import x64

from invglare._core.grids import AngularGrid, ApertureGrid
from invglare.aperture.shapes.stamps import disks_log_transmission
from invglare.optics.fraunhofer import fraunhofer_mft
from invglare.optics.particles import disk_amplitude_mm2, particle_scatter
from invglare.reference.closed_forms import airy_encircled_energy


def test_phased_scatter_matches_a_resolved_raster_of_the_disks():
    """Babinet: opaque disks scatter the field of disk-shaped holes. 12 disks of 7.5 um on a
    0.6 um raster (25 px across each), against the closed form with their phases, 1-4 deg."""
    with x64():
        n, pitch, lam, power = 512, 0.0006, 550.0, 10.0
        # Jittered on a 60 um lattice, so that no two overlap (overlaps block less).
        rng = np.random.default_rng(1)
        lattice = np.stack(np.meshgrid(np.arange(4) - 1.5, np.arange(3) - 1), -1).reshape(-1, 2)
        centres = 0.06 * lattice + rng.uniform(-0.02, 0.02, (12, 2))
        radii = np.full(12, 0.0075)
        grid = ApertureGrid(n, pitch)
        holes = 1.0 - jnp.exp(
            disks_log_transmission(grid, centres, radii, jnp.ones(12), half_px=16)
        )
        out = AngularGrid(96, 0.05)
        # The raster's MFT is normalised to its own power; rescale it to `power`.
        raster = np.array(fraunhofer_mft(holes, grid, lam, out))
        raster *= float(jnp.sum(holes**2)) * pitch**2 / power
        closed = np.asarray(
            particle_scatter(radii, np.ones(12), centres, out, lam, power, "phases")
        )
        r = np.hypot(*np.mgrid[:96, :96] - 48) * 0.05
        ring = (r > 1.0) & (r < 2.3)
        err = np.abs(raster - closed)[ring].max() / closed[ring].max()
        assert err < 0.03, err


def test_ensemble_average_is_n_times_one_disk_and_the_phased_sum_averages_to_it():
    """N random disks: the ensemble term is N |A_1|^2 exactly; the speckled phased sum,
    averaged over 200 draws, within 5 % of it in every annulus from 0.5 to 3 deg."""
    lam, power, n, a = 550.0, 12.0, 40, 0.0075
    out = AngularGrid(64, 0.1)
    radii, amps = np.full(n, a), np.ones(n)
    ensemble = np.asarray(particle_scatter(radii, amps, np.zeros((n, 2)), out, lam, power))
    theta = out.coords_rad()
    f = np.hypot(*np.meshgrid(theta, theta)) / (lam * 1e-6)
    one = (
        np.asarray(disk_amplitude_mm2(a, f)) ** 2 * (float(out.pixel_scale_rad) / (lam * 1e-6)) ** 2
    )
    np.testing.assert_allclose(ensemble, n * one / power, rtol=1e-4)  # float32

    phased = jax.jit(
        jax.vmap(lambda c: particle_scatter(radii, amps, c, out, lam, power, "phases"))
    )
    draws = jax.random.uniform(jax.random.key(0), (200, n, 2), minval=-2.0, maxval=2.0)
    mean = np.asarray(phased(draws)).mean(axis=0)
    r = np.hypot(*np.mgrid[:64, :64] - 32) * 0.1
    for lo in np.arange(0.5, 3.0, 0.5):
        ring = (r >= lo) & (r < lo + 0.5)
        assert mean[ring].mean() == pytest.approx(ensemble[ring].mean(), rel=0.05), lo


def test_babinet_energy_of_one_disk():
    """Over the plane one disk scatters its own area (Parseval): pi a^2 / P, of which the
    +-10 deg square holds the Airy pattern's energy between its inscribed and circumscribed
    circles (97.4 % measured)."""
    a, lam, power = 0.01, 500.0, 3.0
    out = AngularGrid(401, 0.05)
    total = float(
        np.asarray(particle_scatter([a], [1.0], [[0.0, 0.0]], out, lam, power), np.float64).sum()
    )
    full = math.pi * a * a / power
    inner = float(airy_encircled_energy(math.radians(10.0), 2 * a, lam))
    outer = float(airy_encircled_energy(math.radians(10.0 * math.sqrt(2)), 2 * a, lam))
    assert inner * full * 0.999 < total < outer * full * 1.001
