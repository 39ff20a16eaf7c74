"""The hierarchical prior of a fitted lash layout (invglare.fit.lash_prior): free per-lash
leaves are tied to their row's population, in the fit's residuals and the sampler's
density alike, and the population's parameters come out with the errors of a population
estimated from its lashes."""

from __future__ import annotations

import math

import equinox as eqx
import helpers
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from invglare.aperture.eye import EyeAperture, Eyelashes, Eyelids, Pupil
from invglare.config.fit_tables import read_free
from invglare.errors import ConfigError
from invglare.fit import Forward, Observation, Parameter, ParameterSpace
from invglare.fit.lash_prior import LayoutPrior, layout_priors, prior_residuals
from invglare.fit.sample import make_log_posterior
from invglare.fit.views import make_residual_fn
from invglare.models.kakimoto import KakimotoGlare

ROW = "model.aperture.upper_lashes"


def _forward(n_max: int = 12) -> Forward:
    lashes = Eyelashes(
        count=10.5, n_max=n_max, key=jax.random.key(5), lid="upper", mean_angle_deg=2.0,
        angular_spread_deg=8.0, thickness_mm=0.06, length_mm=2.0, curvature_per_mm=0.05,
        root_span_mm=3.0,
    ).with_layout()  # fmt: skip
    eye = EyeAperture(Pupil(2.0), Eyelids(0.7, 1.2), upper_lashes=lashes)
    model = KakimotoGlare.build(
        eye, focal_length_mm=17.0, obstacle_distance_mm=8.0, npix=32, aperture_npix=32,
        colour="spectral", wavelengths_nm=550.0, pixel_scale_deg=0.01,
    )  # fmt: skip
    return Forward(model, Observation(flux=1e5, background=5.0, gain=2.0, read_noise=3.0))


def _angles(fwd) -> np.ndarray:
    return np.asarray(fwd.model.aperture.upper_lashes.layout.angle_deg)


@pytest.mark.slow
def test_free_layout_leaves_carry_the_prior_in_the_residuals_and_the_posterior():
    """Freeing angle_deg[3..5] adds 3 standardised deviations and the normalisation to the
    residuals; their sum of squares is -2 log prior up to the constants, and the sampler's
    log prior holds the same density."""
    with helpers.x64():
        fwd = _forward()
        angles = _angles(fwd)
        params = [
            Parameter(f"{ROW}.layout.angle_deg[{i}]", -40, 40, init=angles[i]) for i in (3, 4, 5)
        ]
        params.append(Parameter(f"{ROW}.mean_angle_deg", -20, 20, init=1.0))
        space = ParameterSpace(params)
        priors = layout_priors(space, fwd)
        assert priors == (
            LayoutPrior(("model", "aperture", "upper_lashes"), (("angle_deg", (3, 4, 5)),)),
        )
        photo = np.asarray(fwd())
        fn = make_residual_fn(space, fwd, photo, {"pixels": 1.0})
        latent = space.initial_latent()
        r = np.asarray(fn(latent, None))
        assert r.shape == (32 * 32 + 4,)
        z = (angles[[3, 4, 5]] - 1.0) / math.hypot(8.0, 0.05)
        np.testing.assert_allclose(r[-4:-1], z, rtol=1e-9)
        log_sd = math.log(math.hypot(8.0, 0.05))
        np.testing.assert_allclose(r[-1] ** 2, 2 * 3 * (log_sd - math.log(0.05)), rtol=1e-9)
        values = space.from_latent(latent)
        density = float(priors[0].log_density(space.apply(fwd, values)))
        expected = -0.5 * np.sum(z**2) - 3 * log_sd - 1.5 * math.log(2 * math.pi)
        assert math.isclose(density, expected, rel_tol=1e-12)
        lp = make_log_posterior(space, fwd, photo)
        without = lp.space.log_prior(values) + lp.space.log_det_jacobian(latent)
        assert math.isclose(float(lp.log_prior(latent) - without), density, rel_tol=1e-12)


def test_population_mean_and_spread_are_those_of_the_lashes_with_honest_errors():
    """With 400 lash angles known (the photo's information, here exact), minimising the
    prior's residuals over the row's mean angle and spread gives the angles' mean and
    their (maximum-likelihood) standard deviation to 1e-6, and the Gauss-Newton error of
    the mean is spread / sqrt(n) within 1 %: the population's error, not a seed's."""
    with helpers.x64():
        rng = np.random.default_rng(0)
        values = rng.normal(3.0, 7.0, 400)
        row = Eyelashes(count=399.5, n_max=400, key=0, angular_spread_deg=5.0).with_layout()
        layout = eqx.tree_at(lambda lay: lay.angle_deg, row.layout, jnp.asarray(values))
        row = eqx.tree_at(lambda r: r.layout, row, layout)
        prior = LayoutPrior((), (("angle_deg", tuple(range(400))),))

        def residuals(y, args):
            r = eqx.tree_at(
                lambda r: (r.mean_angle_deg, r.angular_spread_deg), row, (y[0], jnp.exp(y[1]))
            )
            return prior.residuals(r)

        sol = optx.least_squares(
            residuals, optx.LevenbergMarquardt(1e-10, 1e-12), jnp.asarray([0.0, 1.0])
        )
        mean, spread = float(sol.value[0]), float(np.exp(sol.value[1]))
        sd = math.sqrt(spread**2 + 0.05**2)
        assert abs(mean - values.mean()) < 1e-6
        assert abs(sd - values.std()) < 1e-6 * values.std()
        jac = jax.jacfwd(residuals)(sol.value, None)
        err = math.sqrt(float(np.linalg.inv(np.asarray(jac.T @ jac))[0, 0]))
        assert abs(err / (sd / math.sqrt(400)) - 1.0) < 0.01


def test_vector_leaf_frees_each_element():
    """A [[free]] path naming a whole layout leaf frees every element (or those listed in
    `indices`), each starting from the model's value."""
    fwd = _forward()
    table = {"path": f"{ROW}.layout.root_mm", "lower": -3.0, "upper": 3.0, "indices": [4, 6]}
    params, nuisance, _ = read_free([table], fwd, {})
    assert [p.path for p in params] == [f"{ROW}.layout.root_mm[4]", f"{ROW}.layout.root_mm[6]"]
    roots = np.asarray(fwd.model.aperture.upper_lashes.layout.root_mm)
    assert [p.init for p in params] == pytest.approx(roots[[4, 6]])
    everything, _, _ = read_free([{k: v for k, v in table.items() if k != "indices"}], fwd, {})
    assert len(everything) == 12 and not nuisance
    with pytest.raises(ConfigError, match="indices"):
        read_free([{**table, "indices": [12]}], fwd, {})
    with pytest.raises(ConfigError, match="scalar"):
        read_free([{"path": "obs.flux", "lower": 0, "upper": 1e9, "indices": [0]}], fwd, {})


def test_layout_leaf_outside_a_row_of_lashes_is_refused():
    """Only a row of lashes has a layout prior; prior_residuals of no prior is empty."""
    assert prior_residuals((), None).shape == (0,)
    with pytest.raises(ConfigError, match="row of eyelashes"):
        layout_priors(
            ParameterSpace([Parameter("model.layout.angle_deg[0]", -1, 1, init=0.0)]),
            _FakeTree(),
        )


class _Layout(eqx.Module):
    angle_deg: jax.Array


class _Holder(eqx.Module):
    layout: _Layout


class _FakeTree(eqx.Module):
    model: _Holder = eqx.field(default_factory=lambda: _Holder(_Layout(jnp.zeros(3))))
