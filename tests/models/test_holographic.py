"""The holographic eye model: closed forms, depth, config, bad input, gradients, transforms."""

from __future__ import annotations

import dataclasses
import math
import tomllib
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import x64

from invglare._core.grids import AngularGrid
from invglare.aperture.eye import EyeAperture, Eyelashes, Eyelids, Pupil
from invglare.config.holographic import holographic_from_config
from invglare.config.model import build_model
from invglare.config.raster import GridRequest
from invglare.errors import ConfigError, InputDataError, PhysicsRangeError
from invglare.models.holographic import (
    HolographicEye,
)
from invglare.optics.holographic import Spectacles, TearFilm, bins_to_image, point_response
from invglare.reference.closed_forms import airy_pixel_psf

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "holographic_eye.toml"
RGB = (640.0, 550.0, 460.0)


def _clear_eye(diameter_mm=2.5):
    return EyeAperture(pupil=Pupil(diameter_mm))


def _lash_eye(diameter_mm=3.0):
    return EyeAperture(
        pupil=Pupil(diameter_mm),
        lids=Eyelids(1.6, 1.8),
        upper_lashes=Eyelashes(
            count=12.5, n_max=16, key=3, lid="upper", thickness_mm=0.08, length_mm=2.0
        ),
    )


def _energy_within(psf, radius_px):
    n = psf.shape[0]
    yy, xx = np.mgrid[:n, :n] - n // 2
    return float(psf[np.hypot(yy, xx) <= radius_px].sum())


# ---------------------------------------------------------------------- closed forms


def test_focused_point_at_constant_depth_gives_the_airy_pattern_in_every_channel():
    # A point at 2 m, the lens focused at 2 m, a clear 2.5 mm pupil: each channel's PSF is
    # the Airy pattern of its wavelength at the common pixel scale, in absolute units
    # (energy per pixel, the peak A dtheta^2 / lambda^2). Measured: 3e-4 of the peak.
    model = HolographicEye.build(
        _clear_eye(2.5), npix=128, window_mm=8.0, wavelengths_nm=RGB,
        focus_distance_mm=2000.0, depth_mm=2000.0, layers=("pupil", "lens"),
    )  # fmt: skip
    psf = np.asarray(model.psf())
    grid = AngularGrid(128, model.pixel_scale_deg)
    for c, lam in enumerate(RGB):
        ref = np.asarray(airy_pixel_psf(grid, 2.5, lam))
        assert np.unravel_index(psf[..., c].argmax(), (128, 128)) == (64, 64)
        np.testing.assert_allclose(psf[..., c], ref, atol=1e-3 * ref.max())


def test_defocused_point_gives_a_blur_disk_of_the_geometric_size():
    # Relaxed eye (focus at infinity), a point at 250 mm: 4 D of defocus over a 3 mm pupil
    # (8 waves at the edge). Geometric optics: a uniform disk of angular diameter D * 4 D =
    # 0.012 rad (87.3 px in radius), whose encircled energy is (r / r_geo)^2 inside it; the
    # rim is blurred by diffraction over a few lambda / D (2.7 px). Measured: 0.0625, 0.258,
    # 0.498, 0.567 at 0.25, 0.5, 0.707, 0.75 r_geo; 0.992 within 1.25 r_geo.
    model = HolographicEye.build(
        _clear_eye(3.0), npix=256, window_mm=8.0, wavelengths_nm=(550.0,),
        depth_mm=250.0, layers=("pupil", "lens"),
    )  # fmt: skip
    psf = np.asarray(model.psf())
    r_geo = 0.5 * 3.0 * (1 / 250.0) / model.sampling.pixel_scale_rad  # px
    total = _energy_within(psf, 1e9)
    for frac in (0.25, 0.5, 1 / math.sqrt(2), 0.75):
        ee = _energy_within(psf, frac * r_geo) / total
        assert ee == pytest.approx(frac**2, abs=0.012), (frac, ee)
    assert _energy_within(psf, 1.25 * r_geo) / total > 0.98
    assert _energy_within(psf, 0.5 * r_geo) / total < 0.27  # not a smaller disk either


@pytest.mark.parametrize("waves", [0.25, 0.5])
def test_small_defocus_lowers_the_peak_by_the_closed_form(waves):
    # Defocus W rho^2 (W at the pupil's edge): the on-axis intensity falls to
    # sinc^2(k W / 2) = [sin(pi W / lambda) / (pi W / lambda)]^2 of the focused one;
    # a quarter wave (Rayleigh, the depth-layer rounding criterion) gives 0.811.
    lam, d = 550.0, 2.5
    dv = 2 * waves * lam * 1e-6 / (d / 2) ** 2  # W = a^2 dV / 2
    kw = dict(npix=128, window_mm=8.0, wavelengths_nm=(lam,), layers=("pupil", "lens"))
    focused = HolographicEye.build(_clear_eye(d), focus_distance_mm=2000.0, depth_mm=2000.0, **kw)
    blurred = focused.psf(depth_mm=1.0 / (1 / 2000.0 + dv))
    ratio = float(blurred[64, 64] / focused.psf()[64, 64])
    x = math.pi * waves
    assert ratio == pytest.approx((math.sin(x) / x) ** 2, abs=2e-3)


def test_depth_buffer_focuses_one_point_and_blurs_the_other():
    # Two points, at 2 m (in focus) and 0.5 m (1.5 D too near), one depth layer each: the
    # speckle-free image is each point's PSF at its layer's depth, placed at its pixel.
    model = HolographicEye.build(
        _clear_eye(2.5), npix=128, window_mm=8.0, wavelengths_nm=(550.0,),
        focus_distance_mm=2000.0, layers=("pupil", "lens"), depth_layers=2,
    )  # fmt: skip
    frame = np.zeros((64, 64), np.float32)
    depth = np.full((64, 64), 2.0, np.float32)  # metres
    frame[20, 20], frame[44, 40] = 1.0, 1.0
    depth[44, 40] = 0.5
    img = np.asarray(model.speckle_free_image(frame, depth))[..., 0]
    # Layer centres: 1/4 and 3/4 of the way from 1/2000 to 1/500 per mm.
    lo, hi = 1 / 2000.0, 1 / 500.0
    v_far, v_near = lo + 0.25 * (hi - lo), lo + 0.75 * (hi - lo)
    expected = np.zeros((128, 128))
    for (r, c), v in (((20, 20), v_far), ((44, 40), v_near)):
        psf = np.asarray(model.psf(depth_mm=1.0 / v))
        expected += np.roll(psf, (r + 32 - 64, c + 32 - 64), axis=(0, 1))
    np.testing.assert_allclose(img, expected[32:96, 32:96], atol=1e-5 * expected.max())
    assert img[20, 20] > 5 * img[44, 40]


def test_iterations_converge_to_the_speckle_free_image_through_the_model():
    model = HolographicEye.build(
        _clear_eye(2.5), npix=64, window_mm=8.0, wavelengths_nm=(550.0, 460.0),
        focus_distance_mm=2000.0, depth_mm=2000.0, layers=("pupil", "lens"),
    )  # fmt: skip
    rng = np.random.default_rng(0)
    frame = rng.random((64, 64, 2)).astype(np.float32)  # fills the (periodic) grid
    frame[10, 30] = 50.0
    limit = model.speckle_free_image(frame)
    avg = model.render(frame, key=1, iterations=64)
    assert avg.shape == limit.shape == (64, 64, 2)
    rel = float(jnp.linalg.norm(avg - limit) / jnp.linalg.norm(limit))
    assert rel < 2.0 / math.sqrt(64), rel
    # A clear pupil keeps the frame's brightness: on the periodic grid each channel's total is
    # the frame's times its PSF's energy (below 1 by the light beyond the grid's band).
    energy = np.asarray(model.psf().sum(axis=(0, 1)))
    np.testing.assert_allclose(
        np.asarray(limit.sum(axis=(0, 1))), frame.sum(axis=(0, 1)) * energy, rtol=1e-4
    )
    assert energy.min() > 0.95


def test_input_step_places_fewer_sources_with_the_same_light():
    model = HolographicEye.build(
        _clear_eye(2.5), npix=64, window_mm=8.0, wavelengths_nm=(550.0,),
        focus_distance_mm=2000.0, depth_mm=2000.0, layers=("pupil", "lens"), input_step=2,
    )  # fmt: skip
    frame = np.ones((32, 32), np.float32)  # every other output pixel of the whole grid
    img = np.asarray(model.speckle_free_image(frame))[..., 0]
    assert img.shape == (64, 64)
    psf_energy = float(model.psf().sum())
    # Each source carries the light of the 2 x 2 output pixels it stands for.
    assert float(img.sum()) == pytest.approx(4 * frame.sum() * psf_energy, rel=1e-4)
    # Fewer sources, less detail: the image of a uniform frame is a lattice of PSFs whose
    # period (2 px) the PSF (first zero at 3.9 px) nearly smooths out.
    assert img.std() / img.mean() < 0.2
    with pytest.raises(InputDataError, match="needs a grid"):
        model.speckle_free_image(np.ones((40, 40)))


# ---------------------------------------------------------------------- layers


@pytest.mark.slow
def test_layer_switches_and_base_plane():
    film = TearFilm(0.05, 0.5, key=1, pattern="random")
    kw = dict(npix=64, window_mm=8.0, wavelengths_nm=(550.0,), tear_film=film)
    full = HolographicEye.build(
        _lash_eye(), spectacles=Spectacles(-1.0),
        layers=("spectacles", "lashes", "tear_film", "pupil", "lens"), **kw,
    )  # fmt: skip
    assert full.base_distance_mm == 15.6 and not full.shift_invariant
    no_film = dataclasses.replace(full, layers=("spectacles", "lashes", "pupil", "lens"))
    assert no_film.base_distance_mm == 15.6
    only_pupil = dataclasses.replace(full, layers=("pupil", "lens"))
    assert only_pupil.base_distance_mm == 0.0 and only_pupil.shift_invariant
    # The tear film switched off is the same as no tear film at all.
    without = dataclasses.replace(no_film, tear_film=None)
    np.testing.assert_allclose(np.asarray(no_film.psf()), np.asarray(without.psf()), atol=1e-7)
    # Switching the lashes off is an eye without lids and lashes (and the PSF then changes).
    a = dataclasses.replace(full, layers=("tear_film", "pupil", "lens"))
    b = dataclasses.replace(a, eye=EyeAperture(pupil=a.eye.pupil))
    np.testing.assert_allclose(np.asarray(a.psf()), np.asarray(b.psf()), atol=1e-7)
    assert float(jnp.abs(full.psf() - a.psf()).max()) > 1e-4


@pytest.mark.slow
def test_psf_off_the_axis_moves_to_the_centre_and_changes_only_with_layers_in_front():
    model = HolographicEye.build(
        _lash_eye(), npix=64, window_mm=8.0, wavelengths_nm=(550.0,),
        focus_distance_mm=2000.0, layers=("lashes", "pupil", "lens"),
    )  # fmt: skip
    on, off = model.psf(), model.psf((0.05, -0.04))
    assert int(jnp.argmax(off)) == int(jnp.argmax(on)) == 64 * 32 + 32
    assert float(jnp.abs(on - off).max()) > 1e-4 * float(on.max())
    clear = dataclasses.replace(model, layers=("pupil", "lens"))
    np.testing.assert_allclose(
        np.asarray(clear.psf((0.05, -0.04))), np.asarray(clear.psf()), atol=1e-7
    )


# ---------------------------------------------------------------------- config


def _example_config():
    with EXAMPLE.open("rb") as fh:
        return tomllib.load(fh)


@pytest.mark.slow
def test_example_config_builds_renders_and_round_trips():
    model = build_model(_example_config(), EXAMPLE.parent, npix=64)
    assert model.layers == ("lashes", "tear_film", "pupil", "lens")
    assert model.iterations == 64 and model.wavelengths_nm == RGB
    assert float(model.accommodation_d) == pytest.approx(0.5)
    frame = np.zeros((48, 48, 3), np.float32)
    frame[24, 24] = 100.0
    img = model.render(frame, key=0, iterations=2)
    assert img.shape == (48, 48, 3) and bool(jnp.all(jnp.isfinite(img)))
    again = build_model(model.to_config())
    np.testing.assert_allclose(np.asarray(again.psf()), np.asarray(model.psf()), atol=1e-7)


def test_config_round_trip_rebuilds_the_same_model():
    model = build_model(_example_config(), None, npix=64)
    table = model.to_config()
    again = build_model(table)
    assert again.to_config() == table and model.to_config() == table
    assert again.layers == model.layers and again.npix == model.npix
    assert again.sampling.pixel_scale_rad == pytest.approx(model.sampling.pixel_scale_rad, 1e-14)
    assert again.frustum == model.frustum and again.chunk == model.chunk
    a, b = (eqx.filter(m, eqx.is_inexact_array) for m in (model, again))
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    np.testing.assert_array_equal(
        np.asarray(jax.random.key_data(again.tear_film.key)),
        np.asarray(jax.random.key_data(model.tear_film.key)),
    )


def test_a_pixel_scale_override_replaces_the_configs_window():
    """`--pixel-scale-deg`, or the photo a fit reads, sets the sampling of a config that gives
    `window_mm` (as for every kind); the config giving both is still refused."""
    cfg = _example_config()
    own = build_model(cfg, npix=64)
    model = build_model(cfg, npix=64, pixel_scale_deg=0.9 * own.pixel_scale_deg)
    assert model.pixel_scale_deg == pytest.approx(0.9 * own.pixel_scale_deg, rel=1e-12)
    both = {**cfg, "output": {**cfg["output"], "pixel_scale_deg": 0.003}}
    with pytest.raises(ConfigError, match=r"window_mm or output\.pixel_scale_deg, not both"):
        build_model(both, npix=64)


def test_config_errors_name_the_key():
    cfg = _example_config()
    bad = {**cfg, "model": {**cfg["model"], "windw_mm": 8.0}}
    with pytest.raises(ConfigError, match="unknown key 'windw_mm'"):
        build_model(bad, npix=64)
    bad = {**cfg, "model": {**cfg["model"], "layers": {"lashes": "yes"}}}
    with pytest.raises(ConfigError, match=r"model\.layers\.lashes must be true or false"):
        build_model(bad, npix=64)
    bad = {**cfg, "model": {**cfg["model"], "kind": "eye"}}
    # Through the registry the eye kind's reader names the first key it does not know ...
    with pytest.raises(ConfigError, match="unknown key 'focus_distance_m'"):
        build_model(bad, npix=64)
    # ... and the holographic reader called directly refuses another kind.
    with pytest.raises(ConfigError, match="kind = 'holographic'"):
        holographic_from_config(bad, None, GridRequest(64, None, None), "test")
    bad = {**cfg, "model": {**cfg["model"], "depth_layers": "many"}}
    with pytest.raises(ConfigError, match="depth_layers"):
        build_model(bad, npix=64)


def test_depth_layers_auto_from_the_frustum():
    cfg = _example_config()
    cfg = {**cfg, "model": {**cfg["model"], "depth_layers": "auto"}}
    model = build_model(cfg, npix=64)
    # near 0.3 m, far 100 m, the largest pupil 4 mm, 460 nm: (1/300 - 1/1e5) * 4 / 460e-6.
    assert model.depth_layers == math.ceil((1 / 300 - 1 / 1e5) * 2.0**2 / 460e-6)


# ---------------------------------------------------------------------- bad input


@pytest.fixture(scope="module")
def small():
    return HolographicEye.build(
        _clear_eye(2.5), npix=64, window_mm=8.0, wavelengths_nm=(550.0,),
        focus_distance_mm=2000.0, layers=("pupil", "lens"),
    )  # fmt: skip


def test_depth_buffer_of_another_size_is_refused(small):
    with pytest.raises(InputDataError, match=r"depth buffer has shape \(32, 30\)"):
        small.render(np.ones((32, 32)), np.ones((32, 30)))


@pytest.mark.parametrize(
    "value, match", [(-1.0, "depth -1"), (np.nan, "non-finite"), (0.0, "depth 0")]
)
def test_negative_zero_or_non_finite_depths_are_refused(small, value, match):
    depth = np.full((32, 32), 2.0)
    depth[3, 4] = value
    with pytest.raises(InputDataError, match=match):
        small.speckle_free_image(np.ones((32, 32)), depth)
    with pytest.raises(PhysicsRangeError, match="constant depth"):
        small.render(np.ones((32, 32)), -2.0)


def test_too_near_a_depth_is_refused_with_the_nearest_one(small):
    near = small.nearest_depth_mm()
    with pytest.raises(PhysicsRangeError, match="nearer than this grid resolves"):
        small.speckle_free_image(np.ones((32, 32)), np.full((32, 32), 0.5 * near / 1000))


@pytest.mark.parametrize("focus", [0.0, -1.0, float("nan")])
def test_focus_distance_at_or_below_zero_is_refused(focus):
    with pytest.raises(PhysicsRangeError, match="focus"):
        HolographicEye.build(_clear_eye(), npix=64, focus_distance_mm=focus)
    cfg = _example_config()
    cfg = {**cfg, "model": {**cfg["model"], "focus_distance_m": focus}}
    with pytest.raises(PhysicsRangeError, match="focus_distance_m must be > 0"):
        build_model(cfg, npix=64)


@pytest.mark.parametrize("n", [0, -3, 1.5, True])
def test_iterations_below_one_are_refused(small, n):
    with pytest.raises(ConfigError, match="iterations"):
        small.render(np.ones((32, 32)), iterations=n)
    with pytest.raises(ConfigError, match="iterations"):
        HolographicEye.build(_clear_eye(), npix=64, iterations=n)


def test_aliasing_tear_film_is_refused_with_the_grid_it_needs():
    # A 1 um rms film with 0.1 mm correlation tilts rays by ~5e-3 rad, beyond this grid's
    # half field (32 * 6.9e-5 = 2.2e-3 rad).
    with pytest.raises(PhysicsRangeError, match=r"aliases its angular spectrum.*npix >="):
        HolographicEye.build(
            _clear_eye(), npix=64, window_mm=8.0, wavelengths_nm=(550.0,),
            tear_film=TearFilm(1.0, 0.1, key=0, pattern="random"),
        )  # fmt: skip
    # The same film switched off is no problem.
    HolographicEye.build(
        _clear_eye(), npix=64, window_mm=8.0, wavelengths_nm=(550.0,),
        tear_film=TearFilm(1.0, 0.1, key=0, pattern="random"), layers=("pupil", "lens"),
    )  # fmt: skip


def test_window_lens_and_memory_checks():
    with pytest.raises(PhysicsRangeError, match="need a window"):
        HolographicEye.build(_clear_eye(7.0), npix=64, window_mm=6.0, wavelengths_nm=(550.0,))
    with pytest.raises(PhysicsRangeError, match="aliases its phase"):
        HolographicEye.build(
            _clear_eye(3.0), npix=64, window_mm=8.0, wavelengths_nm=(550.0,),
            focus_distance_mm=100.0,
        )  # fmt: skip
    with pytest.raises(ConfigError, match="memory_budget_mb"):
        HolographicEye.build(_clear_eye(), npix=512, memory_budget_mb=1.0)
    with pytest.raises(InputDataError, match="channels"):
        HolographicEye.build(_clear_eye(), npix=64, wavelengths_nm=RGB).render(np.ones((8, 8, 2)))


# ---------------------------------------------------------------------- gradients


def _grad_model():
    film = TearFilm(0.08, 0.6, key=2, pattern="random")
    return HolographicEye.build(
        _lash_eye(3.0), npix=64, window_mm=8.0, wavelengths_nm=(550.0,),
        focus_distance_mm=2000.0, depth_mm=1500.0, tear_film=film,
        spectacles=Spectacles(-0.5, 0.25, 20.0),
        layers=("spectacles", "lashes", "tear_film", "pupil", "lens"), max_pupil_mm=3.3,
    )  # fmt: skip


_LEAVES = (
    ("eye.pupil.diameter_mm", lambda m: m.eye.pupil.diameter_mm),
    ("accommodation_d", lambda m: m.accommodation_d),
    ("tear_film.amplitude_um", lambda m: m.tear_film.amplitude_um),
    ("tear_film.scale_mm", lambda m: m.tear_film.scale_mm),
    ("eye.upper_lashes.mean_angle_deg", lambda m: m.eye.upper_lashes.mean_angle_deg),
    ("eye.upper_lashes.thickness_mm", lambda m: m.eye.upper_lashes.thickness_mm),
    ("spectacles.sphere_d", lambda m: m.spectacles.sphere_d),
)


@pytest.mark.slow
def test_gradients_of_every_fittable_leaf_match_central_differences():
    # float64; a fixed random weighting of the PSF; one jitted loss of all leaves at once.
    # Central differences at steps of 1e-4 and 1e-6 (relative) converge on the autodiff
    # value. The pupil's soft raster is piecewise smooth (its edge crosses pixel
    # boundaries), so its differences converge linearly down to ~1e-5 mm and the larger
    # step errs by 1e-3: measured relative errors at 1e-5 are 4e-8 (pupil), 2e-9
    # (accommodation, tear film, lash thickness), 5e-9 (lash angle), 5e-10 (spectacles).
    with x64():
        base = _grad_model()
        getters = [g for _, g in _LEAVES]
        x0 = jnp.asarray([float(g(base)) for g in getters])
        w = jnp.asarray(np.random.default_rng(0).random((64, 64)))

        def loss(x):
            m = eqx.tree_at(lambda m: [g(m) for g in getters], base, list(x))
            return jnp.sum(m.psf() * w)

        f = jax.jit(loss)
        grad = np.asarray(jax.jit(jax.grad(loss))(x0))
        for i, (name, _) in enumerate(_LEAVES):
            errors = []
            for rel_step in (1e-4, 1e-6):
                h = rel_step * max(abs(float(x0[i])), 0.1)
                e = jnp.zeros_like(x0).at[i].set(h)
                fd = float((f(x0 + e) - f(x0 - e)) / (2 * h))
                errors.append(abs(fd - grad[i]) / abs(grad[i]))
            assert abs(grad[i]) > 1e-8, name  # every leaf moves the PSF
            assert errors[1] <= 1e-5, (name, grad[i], errors)
            assert errors[1] <= max(errors[0], 1e-6), (name, errors)


# ---------------------------------------------------------------------- transforms


def test_jit_equals_eager_and_vmap_over_keys_equals_a_loop(small):
    frame = np.random.default_rng(1).random((32, 32)).astype(np.float32)
    eager = small.render(frame, key=jax.random.key(5), iterations=2)
    run = eqx.filter_jit(lambda m, k: m.render(frame, key=k, iterations=2))
    np.testing.assert_allclose(
        np.asarray(run(small, jax.random.key(5))), np.asarray(eager), rtol=1e-4, atol=1e-7
    )
    keys = jax.random.split(jax.random.key(0), 3)
    batched = jax.vmap(lambda k: run(small, k))(keys)
    for i in range(3):
        np.testing.assert_allclose(
            np.asarray(batched[i]), np.asarray(run(small, keys[i])), rtol=1e-4, atol=1e-7
        )
    np.testing.assert_allclose(
        np.asarray(eqx.filter_jit(lambda m: m.psf())(small)), np.asarray(small.psf()), atol=1e-7
    )


def test_vmap_over_wavelengths_equals_one_wavelength_at_a_time():
    model = HolographicEye.build(
        _clear_eye(2.5), npix=64, window_mm=8.0, wavelengths_nm=RGB,
        focus_distance_mm=2000.0, tear_film=TearFilm(0.05, 0.5, key=1, pattern="random"),
        layers=("tear_film", "pupil", "lens"),
    )  # fmt: skip
    v = jnp.asarray([1 / 2000.0])

    def psf_at(lam):
        return point_response(model.channel_stack(lam, v), (0, 0))

    batched = jax.jit(jax.vmap(psf_at))(jnp.asarray(RGB))
    one = jax.jit(psf_at)
    for i, lam in enumerate(RGB):
        np.testing.assert_allclose(np.asarray(batched[i]), np.asarray(one(lam)), atol=1e-7)
    np.testing.assert_allclose(
        np.asarray(jnp.moveaxis(model.psf(), -1, 0)), np.asarray(bins_to_image(batched)), atol=1e-6
    )


def test_grad_through_render_with_fixed_phases(small):
    frame = jnp.zeros((32, 32)).at[16, 16].set(1.0)

    def loss(d):
        m = eqx.tree_at(lambda m: m.eye.pupil.diameter_mm, small, d)
        return m.render(frame, key=jax.random.key(0), iterations=2)[16, 16, 0]

    g = jax.grad(loss)(jnp.float32(2.5))
    assert bool(jnp.isfinite(g)) and float(g) > 0  # a wider pupil sharpens the peak


@pytest.mark.slow
def test_cropped_stack_equals_the_full_grid():
    # The layers on the central m x m samples (with the taper) give the full grid's PSF: the
    # pupil's light never crosses the crop's margin. Lashes and tear film in front, on and
    # off the axis; measured: 3e-6 of the peak (float32). With a -0.5 D spectacle lens
    # 15.6 mm in front the two differ by 5e-5 (on the axis) to 8e-4: spectacles default to
    # the full grid.
    film = TearFilm(0.08, 0.6, key=2, pattern="random")
    kw = dict(
        npix=128, window_mm=8.0, wavelengths_nm=(550.0,), focus_distance_mm=2000.0,
        tear_film=film, layers=("lashes", "tear_film", "pupil", "lens"),
    )  # fmt: skip
    cropped = HolographicEye.build(_lash_eye(3.0), **kw)
    full = HolographicEye.build(_lash_eye(3.0), layer_npix=128, **kw)
    assert cropped.layer_npix == 80 and full.layer_npix == 128
    for angle in (None, (0.08, -0.05)):
        a, b = np.asarray(cropped.psf(angle)), np.asarray(full.psf(angle))
        np.testing.assert_allclose(a, b, atol=2e-5 * b.max())
    glasses = dict(kw, spectacles=Spectacles(-0.5), layers=("spectacles", *kw["layers"]))
    assert HolographicEye.build(_lash_eye(3.0), **glasses).layer_npix == 128
    with pytest.raises(PhysicsRangeError, match="layer_npix"):
        HolographicEye.build(_lash_eye(3.0), layer_npix=40, **kw)


def test_progress_bar_path_and_mode_dispatch_give_the_same_images(small):
    frame = np.random.default_rng(2).random((32, 32)).astype(np.float32)
    key = jax.random.key(9)
    plain = small.render(frame, key=key, iterations=3)
    shown = small.render(frame, key=key, iterations=3, progress=True)
    np.testing.assert_allclose(np.asarray(shown), np.asarray(plain), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(
        np.asarray(small.image(frame, key=key, iterations=3)), np.asarray(plain), atol=1e-7
    )
    free = dataclasses.replace(small, mode="speckle_free")
    np.testing.assert_allclose(
        np.asarray(free.image(frame)), np.asarray(small.speckle_free_image(frame)), atol=1e-7
    )


def test_model_interface_methods(small):
    assert HolographicEye.centre == "light" and HolographicEye.animated is False
    assert small.shift_invariant and small.wavelengths_nm == (550.0,)
    psfs = small.batch(jnp.asarray([[0.0, 0.0], [0.05, 0.02]]))
    assert psfs.shape == (2, 64, 64)
    np.testing.assert_allclose(np.asarray(psfs[1]), np.asarray(small()), atol=1e-7)
    # 1.22 lambda / D over the pixel: 1.22 * 550 nm / 2.5 mm / (550 nm / 8 mm) = 3.9 px.
    assert small.core_radius_px() == pytest.approx(1.22 * 8.0 / 2.5)
    assert small.header()["layers"] == ["pupil", "lens"]
    with pytest.raises(ConfigError, match="static model"):
        small(state=1)
    with pytest.raises(PhysicsRangeError, match=r"shape \(2,\)"):
        small(jnp.zeros(3))
    wide = eqx.tree_at(lambda m: m.eye.pupil.diameter_mm, small, 3.5)
    sized = small.sized_for([wide])
    assert sized.max_pupil_mm == 3.5 and sized.layer_npix >= small.layer_npix
    with pytest.raises(PhysicsRangeError, match="need a window"):
        small.sized_for([eqx.tree_at(lambda m: m.eye.pupil.diameter_mm, small, 7.9)])
