"""Staged fits and starts (invglare.fit.stages, invglare.fit.starts) on a cheap Gaussian PSF:
the scan keeps the best points and matches their flux, stages hold and hand on values, the
callbacks report, starts and guesses come from the photo and the model."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import x64
from jaxtyping import Array, Float

from invglare.errors import ConfigError
from invglare.fit import Forward, Observation, Parameter, ParameterSpace, make_residual_fn
from invglare.fit.params import START_MARGIN
from invglare.fit.stages import (
    ScanProgress,
    Stage,
    StageDone,
    branched_starts,
    fit_staged,
    hold,
    scan,
)
from invglare.fit.starts import centre_guess, default_init, draw_starts, photo_guesses

SIGMA = "model.sigma_px"


@pytest.fixture(autouse=True)
def _float64():
    with x64():
        yield


class Gauss(eqx.Module):
    """A unit-energy Gaussian PSF on a 24-px grid."""

    sigma_px: Float[Array, ""] = eqx.field(converter=jnp.asarray)

    def __call__(self):
        x = jnp.arange(24, dtype=self.sigma_px.dtype) - 12
        g = jnp.exp(-(x[None, :] ** 2 + x[:, None] ** 2) / (2 * self.sigma_px**2))
        return g / jnp.sum(g)


@pytest.fixture(scope="module")
def problem():
    """A photo of sigma 2.2 px, flux 5e4, background 10, offset (0.4, -0.3) px, with noise."""
    with x64():
        truth = Observation(flux=5e4, background=10.0, dx_px=0.4, dy_px=-0.3, read_noise=2.0)
        target = np.asarray(truth.sample(jax.random.key(0), Gauss(2.2)()))
        guess = Observation.from_target(target, read_noise=2.0)
        space = ParameterSpace(
            [Parameter(SIGMA, 1.0, 5.0, init=3.0)],
            nuisance=[
                Parameter("obs.flux", 0.0, math.inf, init=float(guess.flux)),
                Parameter("obs.dx_px", -2.0, 2.0, init=0.0),
                Parameter("obs.dy_px", -2.0, 2.0, init=0.0),
            ],
        )
        yield space, Forward(Gauss(3.0), guess), target


def test_scan_keeps_the_lowest_losses_and_matches_the_flux(problem):
    space, forward, target = problem
    points = draw_starts(space, {}, 12, seed=1)
    points[:, 1] = 1e3  # a flux 50x too low: every point gets the photo's instead
    reports = []
    starts, record = scan(
        space, forward, target, {"radial": 1.0}, points, n=3, progress=reports.append
    )
    assert reports[0] == ScanProgress(0, 12, ("radial",)) and reports[-1].done == 12
    assert len(reports) == 13
    assert starts.shape == (3, 4) and record["n_points"] == 12
    losses = np.asarray(record["losses"])
    assert list(record["kept"]) == list(np.argsort(losses, kind="stable")[:3])
    assert np.allclose(starts, record["starts"])
    # The matched flux is the photo's excess over the background, per unit of PSF: 5e4
    # within the noise (the guessed background is the photo's edge).
    assert np.all(np.abs(starts[:, 1] / 5e4 - 1) < 0.05), starts[:, 1]
    # The loss of a kept point is the loss there with that flux.
    fn = make_residual_fn(space, forward, target, {"radial": 1.0})
    best = record["kept"][0]
    assert float(fn.loss(space.to_latent(starts[0]))) == pytest.approx(losses[best], rel=1e-9)
    assert record["points"][best] == {SIGMA: pytest.approx(points[best, 0])}


def test_hold_writes_the_held_values_and_drops_their_columns(problem):
    space, forward, _ = problem
    starts = np.array([[2.0, 4e4, 0.3, -0.1], [2.5, 4e4, 0.3, -0.1]])
    sub, template, free, held = hold(space, forward, starts, ("obs.dx_px", "obs.dy_px"))
    assert sub.paths == (SIGMA, "obs.flux") and free.tolist() == starts[:, :2].tolist()
    assert held == {"obs.dx_px": 0.3, "obs.dy_px": -0.1}
    assert float(template.obs.dx_px) == 0.3 and float(template.obs.dy_px) == -0.1
    same = hold(space, forward, starts, ())
    assert same[0] is space and same[1] is forward and same[3] == {}


def test_staged_fit_hands_the_best_stage_on_and_records_every_stage(problem):
    space, forward, target = problem
    starts = draw_starts(space, {}, 3, seed=0)
    stage = Stage({"radial": 1.0}, 30, ("obs.dx_px", "obs.dy_px"))
    done, steps = [], []
    result = fit_staged(
        space, forward, target, {"pixels": 1.0}, starts, stages=[stage],
        scan_points=draw_starts(space, {}, 8, seed=2), progress=steps.append,
        stage_done=done.append, max_steps=40, batch="loop",
    )  # fmt: skip
    first, last = result.stages
    assert first["views"] == {"radial": 1.0} and len(first["final_loss"]) == 3
    assert "scan" in first and first["scan"]["n_points"] == 8
    assert last["views"] == {"pixels": 1.0} and last["origin"] == [result.best_start]
    assert [d.number for d in done] == [1, 2] and isinstance(done[0], StageDone)
    assert set(done[1].values) == {SIGMA} and done[1].loss == result.loss
    assert {p.stage for p in steps} == {0, 1} and {p.n_stages for p in steps} == {2}
    # The starts on record are the scan's picks (with their matched flux).
    assert [[s[p] for p in space.paths] for s in result.starts] == first["scan"]["starts"]
    assert "(stage 2 of 2; from the best of 3 starts" in result.message
    assert result.n_steps == first["n_steps"][result.best_start] + last["n_steps"][0]
    assert abs(result.values[SIGMA] - 2.2) < 0.05 and abs(result.values["obs.dx_px"] - 0.4) < 0.05
    # The first stage alone, then the final fit from its best values: the same result.
    early = fit_staged(
        space, forward, target, {"pixels": 1.0}, starts, stages=[stage], final=False,
        max_steps=40, batch="loop",
    )  # fmt: skip
    assert len(early.stages) == 1
    resumed = fit_staged(
        space, forward, target, {"pixels": 1.0}, starts, stages=[stage], resume=early,
        max_steps=40, batch="loop",
    )  # fmt: skip
    assert len(resumed.stages) == 2 and resumed.starts == early.starts
    with pytest.raises(ConfigError, match="final=False needs stages"):
        fit_staged(space, forward, target, {"pixels": 1.0}, starts, final=False)


def test_branched_starts_round_offset_and_stay_inside_the_bounds(problem):
    space, _, _ = problem  # sigma in [1, 5], dx and dy in [-2, 2]
    best = np.array([2.6, 4e4, 0.3, -1.4])
    assert branched_starts(space, best, ()).tolist() == [best.tolist()]
    starts = branched_starts(space, best, [(SIGMA, (-2, -1, 0, 1, 3))])
    margin = 1e-3 * 4.0  # of the width: a start never sits on a bound
    assert starts[:, 0].tolist() == pytest.approx([1.0 + margin, 2.0, 3.0, 4.0, 5.0 - margin])
    assert np.all(starts[:, 1:] == best[1:])
    # Two branches multiply: every sigma with every dy.
    both = branched_starts(space, best, [(SIGMA, (0, 1)), ("obs.dy_px", (0, 1))])
    assert [tuple(r) for r in both[:, [0, 3]]] == [(3.0, -1.0), (3.0, 0.0), (4.0, -1.0), (4.0, 0.0)]


def test_a_stage_branches_its_best_into_the_next_stages_starts(problem):
    space, forward, target = problem
    starts = draw_starts(space, {}, 2, seed=0)
    stage = Stage({"radial": 1.0}, 30, ("obs.dx_px", "obs.dy_px"), ((SIGMA, (-1, 0, 1)),))
    result = fit_staged(
        space, forward, target, {"pixels": 1.0}, starts, stages=[stage], max_steps=40,
        batch="loop",
    )  # fmt: skip
    first, last = result.stages
    assert len(first["final_loss"]) == 2 and len(last["final_loss"]) == 3
    # Every final start descends from the first stage's best start; the best of them wins.
    assert last["origin"] == [result.best_start] * 3
    assert result.loss == pytest.approx(min(last["final_loss"]))
    assert abs(result.values[SIGMA] - 2.2) < 0.05


def test_centre_guess_finds_the_core_and_guesses_stay_inside_the_bounds(problem):
    _, forward, target = problem
    c = centre_guess(target, float(forward.obs.background))
    assert abs(c["obs.dx_px"] - 0.4) < 0.1 and abs(c["obs.dy_px"] + 0.3) < 0.1
    assert centre_guess(np.zeros((8, 8))) == {}
    guesses = photo_guesses(target, forward.obs)
    assert guesses["obs.flux"] == float(forward.obs.flux) and "obs.dx_px" in guesses
    # A guess outside finite bounds moves 1 % of the width inside; a model value outside
    # them gives the middle; without a guess the model's value is the init.
    assert default_init(forward, "obs.dx_px", -0.2, 0.2, guesses) == pytest.approx(0.196)
    assert default_init(forward, SIGMA, 1.0, 2.0, {}) == 1.5
    assert default_init(forward, SIGMA, 1.0, 5.0, {}) == 3.0
    assert default_init(forward, "obs.flux", 0.0, math.inf, {"obs.flux": -5.0}) == -5.0


def test_draw_starts_is_a_latin_hypercube_with_init_ranges_stratified():
    space = ParameterSpace(
        [Parameter("a", 0.0, 1.0, init=0.5), Parameter("b", 0.0, 10.0, init=5.0)],
        nuisance=[Parameter("c", 0.0, 1.0, init=0.25)],
    )
    starts = draw_starts(space, {1: (2.0, 4.0)}, 5, seed=3)
    assert starts.shape == (5, 3) and starts.dtype == np.float64
    np.testing.assert_array_equal(starts, draw_starts(space, {1: (2.0, 4.0)}, 5, seed=3))
    np.testing.assert_allclose(starts[:, 2], 0.25, rtol=1e-12)  # nuisances at their init
    # One start per fifth of the bounds (less the sampler's margins), and of the init range.
    u_bounds = (starts[:, 0] - START_MARGIN) / (1 - 2 * START_MARGIN)
    u_range = (starts[:, 1] - 2.0) / 2.0
    for u in (u_bounds, u_range):
        assert sorted(np.floor(5 * u)) == [0, 1, 2, 3, 4], u
