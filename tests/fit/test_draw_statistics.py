"""Fits of eyes the model did not draw: other draws (invglare.fit.redraw), the scatter of
statistics between eyes (invglare.fit.draw_scatter) and trend Jacobians
(invglare.fit.trend_jacobian). A 48² daylight eye keeps the file quick."""

from __future__ import annotations

import math

import equinox as eqx
import helpers
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from invglare.aperture.eye import EyeAperture, Eyelashes, Eyelids, Particles, Pupil
from invglare.errors import ConfigError
from invglare.fit import Forward, Observation, Parameter, ParameterSpace
from invglare.fit.draw_scatter import estimate_scatter, scatter_covariance, scatter_options
from invglare.fit.redraw import mean_prediction, random_keys, redraw
from invglare.fit.trend_jacobian import COUNT_STEP, TREND_STEP, trend_steps
from invglare.fit.views import make_residual_fn
from invglare.models.kakimoto import KakimotoGlare

PUPIL = "model.aperture.pupil.diameter_mm"
COUNT = "model.aperture.upper_lashes.count"
N = 48


def _forward(seed: int = 7, count: float = 14.4, dx: float = 0.3, dy: float = -0.2) -> Forward:
    lashes = Eyelashes(
        count=count, n_max=20, key=jax.random.key(seed), lid="upper", angular_spread_deg=12.0,
        thickness_mm=0.06, length_mm=2.5, curvature_per_mm=0.05, root_span_mm=5.0,
    )  # fmt: skip
    cells = Particles(
        count=30.0, n_max=30, key=jax.random.key(seed + 1), region="cornea",
        radius_mean_mm=0.01, region_radius_mm=2.0,
    )  # fmt: skip
    eye = EyeAperture(Pupil(2.8), Eyelids(1.2, 1.4), upper_lashes=lashes, particles=(cells,))
    model = KakimotoGlare.build(
        eye, focal_length_mm=17.0, obstacle_distance_mm=8.0, npix=N, aperture_npix=64,
        colour="spectral", wavelengths_nm=550.0, pixel_scale_deg=0.004, window_mm=3.4,
    )  # fmt: skip
    obs = Observation(
        flux=1e6, background=10.0, dx_px=dx, dy_px=dy, gain=2.0, read_noise=3.0, saturation=6e4
    )
    return Forward(model, obs)


def _photo(fwd: Forward, seed: int = 0) -> np.ndarray:
    return np.asarray(fwd.obs.sample(jax.random.key(seed), fwd.psf()))


def _space(count_init: float = 14.4) -> ParameterSpace:
    return ParameterSpace(
        [Parameter(PUPIL, 2.0, 4.0, init=2.8), Parameter(COUNT, 5.0, 19.5, init=count_init)],
        [Parameter("obs.dx_px", -2, 2, init=0.3), Parameter("obs.dy_px", -2, 2, init=-0.2)],
    )


def _whitened_radial(draws: int):
    """The eye's radial view whitened by the scatter of `draws` other eyes measured at the
    start (call under x64): forward, space, start, the options asked for and measured, and
    the whitened residual function."""
    fwd, space = _forward(), _space()
    z = space.initial_latent()
    options = {"radial": {"n_bins": 12, "draws": draws}}
    first = make_residual_fn(space, fwd, _photo(fwd), {"radial": 1.0}, view_options=options)
    measured = scatter_options(first, z, options)
    fn = make_residual_fn(space, fwd, _photo(fwd), {"radial": 1.0}, view_options=measured)
    return fwd, space, z, options, measured, fn


@pytest.mark.slow
def test_redraw_draws_another_eye_with_the_same_parameters():
    """Each random key is replaced (lashes and cells differ), nothing else; a lash layout
    has no key and stays."""
    with helpers.x64():
        fwd = _forward()
        assert random_keys(fwd) == 2
        other = redraw(fwd, jax.random.key(1))
        assert float(jnp.max(jnp.abs(other.psf() - fwd.psf()))) > 1e-4
        assert float(other.model.aperture.pupil.diameter_mm) == 2.8
        fixed = eqx.tree_at(
            lambda f: f.model.aperture.upper_lashes,
            fwd,
            fwd.model.aperture.upper_lashes.with_layout(),
        )
        moved = redraw(fixed, jax.random.key(1))
        np.testing.assert_array_equal(
            np.asarray(moved.model.aperture.upper_lashes.layout.root_mm),
            np.asarray(fixed.model.aperture.upper_lashes.layout.root_mm),
        )
        one, _ = mean_prediction(fwd, 1)
        np.testing.assert_allclose(np.asarray(one), np.asarray(fwd.expected()), rtol=1e-12)


@pytest.mark.slow
def test_trend_steps_and_trend_jacobian():
    """Views with draws differentiate by central differences: a count by +-2 elements, the
    rest by 0.1 latent units. The pupil's column is the central difference of the exact
    residuals over its step (to rounding), and follows their exact derivative to 15 % in
    norm (measured 9 %: the radial profile's curvature over +-0.1 latent units)."""
    with helpers.x64():
        fwd = _forward()
        photo = _photo(_forward(seed=31))
        space = _space()
        steps = trend_steps(space)
        slope = float(space.all[1].dx_dz(space.all[1].to_latent(jnp.asarray(14.4))))
        assert steps[0] == TREND_STEP and steps[1] == pytest.approx(COUNT_STEP / slope)
        views = {"radial": 1.0}
        fn = make_residual_fn(
            space, fwd, photo, views, view_options={"radial": {"n_bins": 12, "draws": 8}}
        )
        assert fn.trend_step == steps
        exact = make_residual_fn(space, fwd, photo, views, view_options={"radial": {"n_bins": 12}})
        assert exact.trend_step == ()
        z = space.initial_latent()
        # The pupil's column of each Jacobian (all the test checks) as one forward
        # derivative along it: the same column as jacfwd's, without the other three, and
        # its eager operations have the residuals' own shapes (compiled once for both).
        e = jnp.zeros_like(z).at[0].set(1.0)
        trend = jax.jvp(lambda y: fn(y, None), (z,), (e,))[1]
        smooth = jax.jvp(lambda y: exact(y, None), (z,), (e,))[1]
        h = steps[0]
        e0 = h * e
        central = (exact(z + e0, None) - exact(z - e0, None)) / (2.0 * h)
        np.testing.assert_allclose(np.asarray(trend), np.asarray(central), rtol=1e-8, atol=1e-10)
        gap = float(jnp.linalg.norm(trend - smooth) / jnp.linalg.norm(smooth))
        assert gap < 0.15, gap


@pytest.mark.slow
def test_whitened_statistics_of_other_eyes_are_unit_normal():
    """The radial and angular views whitened by the scatter of 64 simulated eyes: for 24
    other eyes (other seeds, other noise) at the same parameters, the whitened residuals
    have mean square 1 within 0.25 (sampling and shrinkage), while without whitening the
    angular residuals' mean square is far from 1."""
    with helpers.x64():
        fwd = _forward()
        space = _space()
        z = space.initial_latent()
        options = {"radial": {"n_bins": 12, "draws": 64}, "angular": {"n_bins": 24, "draws": 64}}
        views = {"radial": 1.0, "angular": 1.0}
        base = make_residual_fn(space, fwd, _photo(fwd), views, view_options=options)
        measured = scatter_options(base, z, options)
        assert set(measured["radial"]) >= {"offset", "whiten"}
        squares, raw = [], []
        for k in range(24):
            photo = _photo(_forward(seed=1000 + k), seed=k + 50)
            fn = make_residual_fn(space, fwd, photo, views, view_options=measured)
            squares.append(float(jnp.mean(fn(z, None) ** 2)))
            plain = make_residual_fn(space, fwd, photo, views, view_options=options)
            raw.append(float(jnp.mean(plain.per_view(z)["angular"] ** 2)))
        assert abs(np.mean(squares) - 1.0) < 0.25, np.mean(squares)
        assert abs(np.mean(raw) - 1.0) > 0.5, np.mean(raw)


def test_whitened_residuals_reuse_the_measurements_programs():
    """Residuals whitened by a measured scatter (those the scatter covariance simulates)
    have the same raw statistics: measured again, they give the same offsets and whitening
    and run the program the first measurement compiled, as does the scatter covariance (its
    residual vectors assembled from the raw statistics as the fit assembles its own); its
    gain and the fit's covariance share one compiled Jacobian (each of these programs took
    tens of seconds to compile for a bundled eye). The scatter covariance of 16 other eyes is
    a positive covariance of the four free parameters.

    (The positive-covariance check was a test of its own, which compiled its own
    measurement and Jacobian for a scatter measured from 16 eyes: it shares this one's.)"""
    from invglare.fit.draw_scatter import _draw_batch, _residual_vectors
    from invglare.fit.solve import _information, _jacobian_and_residuals

    with helpers.x64():
        fwd, space, z, options, measured, again = _whitened_radial(8)
        assert again.views[0].whiten is not None
        simulations = _draw_batch._cached._cache_size()
        repeat = scatter_options(again, z, options)
        assert _draw_batch._cached._cache_size() == simulations
        for key in ("offset", "whiten"):
            np.testing.assert_array_equal(repeat["radial"][key], measured["radial"][key])
        compiled = _jacobian_and_residuals._cached._cache_size()
        jac, _ = _information(again, z)
        cov = scatter_covariance(again, z, 16)
        assert _jacobian_and_residuals._cached._cache_size() == compiled + 1
        assert cov.shape == (4, 4)
        assert np.all(np.linalg.eigvalsh(cov) > 0) and np.allclose(cov, cov.T)
        assert _draw_batch._cached._cache_size() == simulations
        # Views weighted, one whitened and one not: assembled as the fit assembles them.
        mixed_options = {"radial": measured["radial"], "angular": {"n_bins": 8}}
        mixed = make_residual_fn(space, fwd, _photo(fwd, seed=3), {"radial": 2.0, "angular": 0.5},
                                 view_options=mixed_options)  # fmt: skip
        ctx = mixed.context(z)
        raw = [np.asarray(v.raw(ctx))[None] for v in mixed.views]
        own = np.asarray(mixed(z))
        np.testing.assert_allclose(_residual_vectors(mixed, raw, own.size)[0], own, rtol=1e-12)
        np.testing.assert_array_equal(jac, _jacobian_and_residuals(again, z)[0])


def test_bad_draw_requests_are_refused():
    with helpers.x64():
        fwd = _forward()
        space = _space()
        z = space.initial_latent()
        fn = make_residual_fn(space, fwd, _photo(fwd), {"radial": 1.0})
        with pytest.raises(ConfigError, match=">= 8"):
            estimate_scatter(fn, z, {"radial": 4})
        with pytest.raises(ConfigError, match="does not use"):
            estimate_scatter(fn, z, {"halo": 16})
        keyless = redraw(fwd, jax.random.key(0))
        keyless = eqx.tree_at(
            lambda f: (f.model.aperture.upper_lashes, f.model.aperture.particles),
            keyless,
            (None, ()),
            is_leaf=lambda x: x is None,
        )
        fn = make_residual_fn(
            space.__class__([space.all[0]]), keyless, _photo(fwd), {"radial": 1.0}
        )
        with pytest.raises(ConfigError, match="no random draws"):
            estimate_scatter(fn, space.__class__([space.all[0]]).initial_latent(), {"radial": 8})
    assert math.isfinite(TREND_STEP)
