"""The fit's one likelihood: deviance residuals, unbiased estimates, calibrated errors, flags.

The photos here are made with other seeds than any fit uses, with Poisson–Gaussian noise
(gain 2, read noise 3) and, in the Monte-Carlo problem, a clipped core. Everything runs in
float64.
"""

import functools
import json
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import GaussPSF, assert_grad_converges, x64

from invglare.fit import (
    FitResult,
    Forward,
    Observation,
    Parameter,
    ParameterSpace,
    deviance_residuals,
    fit,
    fit_photos,
    likelihood_peak,
    make_residual_fn,
)
from invglare.fit.deviance import pixel_log_likelihood_gradient
from invglare.fit.photos import solve_photos
from invglare.fit.report import ReportInfo, write_report
from invglare.fit.sample import make_log_posterior, sample
from invglare.fit.trust import chi2_cause, fit_flags, parameter_flags

GAIN, READ = 2.0, 3.0
SIGMA, FLUX, BACKGROUND, DX, DY = 1.8, 3e4, 20.0, 0.3, -0.2
SATURATION = 1200.0  # the 4-5 brightest pixels of a 1494-count peak are clipped
TRUTH = {
    "model.sigma_px": SIGMA,
    "obs.flux": FLUX,
    "obs.background": BACKGROUND,
    "obs.dx_px": DX,
    "obs.dy_px": DY,
}


@pytest.fixture(autouse=True)
def _float64():
    with x64():
        yield


def blob_problem():
    """A 32² Gaussian blob (sigma, flux, background and centre free), its clip level set."""
    truth = Observation(
        flux=FLUX, background=BACKGROUND, dx_px=DX, dy_px=DY, gain=GAIN, read_noise=READ,
        saturation=SATURATION,
    )  # fmt: skip
    guess = Observation(
        flux=2.8e4, background=18.0, gain=GAIN, read_noise=READ, saturation=SATURATION
    )
    space = ParameterSpace(
        [Parameter("model.sigma_px", 1.0, 4.0, init=2.0)],
        nuisance=[
            Parameter("obs.flux", 0.0, math.inf, init=2.8e4),
            Parameter("obs.background", -50.0, 200.0, init=18.0),
            Parameter("obs.dx_px", -2.0, 2.0, init=0.0),
            Parameter("obs.dy_px", -2.0, 2.0, init=0.0),
        ],
    )
    return truth, Forward(GaussPSF(2.0, 32), guess), space


@eqx.filter_jit
def _noisy_photos(truth: Observation, psf, keys):
    return jax.vmap(lambda k: truth.sample(k, psf))(keys)


def photos(truth: Observation, n: int, seed: int, sigma: float = SIGMA, npix: int = 32):
    # Compiled once per shape, every noise model's values its arguments: an eager vmap of
    # the sampling compiled each of its operations anew for every stack (the flat-field
    # test's six stacks took 30 s of CPU that way).
    psf = GaussPSF(sigma, npix)()
    keys = jax.random.split(jax.random.key(seed), n)
    return np.asarray(_noisy_photos(truth, psf, keys))


# --------------------------------------------------------------------------------------
# the residuals


#: (observed, expected) counts: well above the peak, near it, below, a dark pixel on the
#: constant-variance side, across the variance's kink, bright.
PAIRS = [(60.0, 50.0), (60.0, 59.0), (60.0, 75.0), (-4.0, -1.0), (-4.0, 3.0), (4e4, 3.9e4)]


@pytest.mark.parametrize("o, e", PAIRS)
def test_deviance_residual_gradients_converge_to_finite_differences(o, e):
    """d r / d mean, d r / d gain and d r / d read noise: autodiff against central
    differences at two steps (1e-4 and 2.5e-5 of the value's scale), float64."""
    for name, f, x in (
        ("mean", lambda v: deviance_residuals(o, v, GAIN, READ), e),
        ("gain", lambda v: deviance_residuals(o, e, v, READ), GAIN),
        ("read noise", lambda v: deviance_residuals(o, e, GAIN, v), READ),
    ):
        assert_grad_converges(f, x, 1e-4 * max(abs(x), 1.0), err_msg=f"{name} at {o}, {e}")


@pytest.mark.parametrize("o", [-20.0, -1.0, 0.0, 0.3, 5.0, 60.0, 4e4])
def test_likelihood_peak_and_the_residual_identity(o):
    """`mu*` maximises the pixel's likelihood (a fine grid finds nothing higher); at `mu*`
    the residual is 0; and ``r**2 / 2 = l(mu*) - l(mu)``, ``d(r**2 / 2)/dmu = -dl/dmu``."""
    mu_s, v_s = (float(a) for a in likelihood_peak(o, GAIN, READ))

    def ell(mu):
        v = np.maximum(mu, 0.0) / GAIN + READ**2
        return -0.5 * ((o - mu) ** 2 / v + np.log(v))

    grid = mu_s + np.linspace(-3, 3, 60001) * math.sqrt(v_s)
    assert ell(grid).max() <= ell(mu_s) + 1e-12
    assert v_s == pytest.approx(max(mu_s, 0.0) / GAIN + READ**2)
    assert float(deviance_residuals(o, mu_s, GAIN, READ)) == pytest.approx(0.0, abs=1e-7)
    mus = jnp.asarray(mu_s + np.array([-40.0, -3.0, -0.2, 0.2, 3.0, 40.0]))
    r = np.asarray(deviance_residuals(o, mus, GAIN, READ))
    np.testing.assert_allclose(r**2 / 2, ell(mu_s) - ell(np.asarray(mus)), rtol=1e-9, atol=1e-12)
    assert np.all(np.sign(r) == np.sign(mu_s - np.asarray(mus)))
    half = jax.vmap(jax.grad(lambda m: 0.5 * deviance_residuals(o, m, GAIN, READ) ** 2))(mus)
    score = pixel_log_likelihood_gradient(o, mus, GAIN, READ)
    np.testing.assert_allclose(half, -score, rtol=1e-8, atol=1e-14)


@pytest.mark.slow
def test_half_sum_of_squares_is_the_samplers_negative_log_likelihood():
    """For the whole photo, clipped core included: ``sum(r**2) / 2 + log L`` is the same at
    three parameter points (a constant of the data), and its gradient in every free
    parameter is ``-d log L``, with ``log L`` the sampler's (`make_log_posterior`)."""
    truth, template, space = blob_problem()
    target = photos(truth, 1, seed=3)[0]
    assert (target >= SATURATION).sum() >= 3
    fn = make_residual_fn(space, template, target, {"pixels": 1.0})
    lp = make_log_posterior(space, template, target)

    def half(z):
        r = fn(z, None)
        return 0.5 * jnp.sum(r * r)

    # Each side compiled once (value and gradient) for the three points: evaluated eagerly,
    # every operation of the residuals and of the log-likelihood compiled on its own.
    half_and_grad = jax.jit(jax.value_and_grad(half))
    ll_and_grad = jax.jit(jax.value_and_grad(lambda z: lp.log_likelihood(z)))
    consts = []
    for values in (
        [2.0, 2.8e4, 18.0, 0.0, 0.0],
        [1.8, 3e4, 20.0, 0.3, -0.2],
        [2.5, 4e4, 25.0, -1, 1],
    ):
        z = space.to_latent(jnp.asarray(values))
        (h, dh), (ll, dll) = half_and_grad(z), ll_and_grad(z)
        consts.append(float(h + ll))
        np.testing.assert_allclose(dh, -dll, rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(consts, consts[0], rtol=1e-12)
    # The residual vector's Jacobian in each latent (a weighted sum of the residuals)
    # converges to central differences. One program for every latent (its index traced)
    # and one gradient for all of them: autodiff's value of each column is that gradient's
    # component.
    z0 = space.to_latent(jnp.asarray([1.9, 2.9e4, 19.0, 0.2, -0.1]))
    weights = jnp.asarray(np.random.default_rng(0).normal(size=target.size))
    along = jax.jit(lambda x, i: jnp.sum(weights * fn(z0.at[i].set(x), None)))
    grads = np.asarray(jax.jit(jax.grad(lambda z: jnp.sum(weights * fn(z, None))))(z0))
    for i, path in enumerate(space.paths):
        f = functools.partial(along, i=jnp.asarray(i))
        assert_grad_converges(f, float(z0[i]), 2e-5, grad=grads[i], err_msg=path)  # latent steps


# --------------------------------------------------------------------------------------
# unbiased and calibrated


LEVELS = (20.0, 50.0, 100.0, 200.0, 500.0, 1000.0)


@pytest.mark.slow
def test_flat_field_background_unbiased_within_0_02_counts():
    """200 flat 64² photos per level (20 to 1000 counts, gain 2, read noise 3), background
    fitted by the likelihood: mean(fitted - photo mean) within 0.02 counts of 0 at every
    level. (The photo's mean is unbiased, so this is the estimate's bias, with a Monte-Carlo
    error of ~4e-4 where the error against the truth would be ~0.025 at 1000 counts.)
    Measured: |bias| < 1e-3 everywhere. The same fits in the generalised-Anscombe domain,
    the fit's old final objective, are 0.12-0.13 counts low: the test tells them apart."""
    n = 200
    space = ParameterSpace([Parameter("obs.background", -100.0, 5000.0, init=100.0)])
    template = Forward(GaussPSF(2.0, 64), Observation(flux=0.0, gain=GAIN, read_noise=READ))
    stacks = [photos(Observation(flux=0.0, background=b, gain=GAIN, read_noise=READ), n, 7 + i,
                     npix=64) for i, b in enumerate(LEVELS)]  # fmt: skip
    stack = np.concatenate(stacks)
    fits = fit_photos(space, template, stack)
    assert fits.converged.all()
    bias = (fits.values[:, 0] - stack.mean(axis=(1, 2))).reshape(len(LEVELS), n).mean(axis=1)
    print("likelihood bias per level:", dict(zip(LEVELS, np.round(bias, 5), strict=True)))
    assert np.all(np.abs(bias) < 0.02), bias
    # Errors are the inverse Fisher information: the scatter of the estimates.
    spread = fits.values[:, 0].reshape(len(LEVELS), n).std(axis=1)
    stderr = fits.stderr[:, 0].reshape(len(LEVELS), n).mean(axis=1)
    np.testing.assert_allclose(stderr, spread, rtol=0.15)
    # The Anscombe domain (same photos, same solver): biased low at every level.
    anscombe = make_residual_fn(
        space, template, stack[0], {"pixels": 1.0},
        view_options={"pixels": {"domain": "anscombe"}},
    )  # fmt: skip
    z, *_ = solve_photos(
        anscombe, space.initial_latent(), jnp.asarray(stack), jnp.zeros(stack.shape, bool)
    )
    old = np.asarray(space.from_latent(z))[:, 0] - stack.mean(axis=(1, 2))
    old_bias = old.reshape(len(LEVELS), n).mean(axis=1)
    print("anscombe bias per level:", dict(zip(LEVELS, np.round(old_bias, 4), strict=True)))
    assert np.all(old_bias < -0.1), old_bias


@pytest.fixture(scope="module")
def monte_carlo():
    """1000 noise draws of the blob problem, each fitted by `fit_photos` from one start."""
    with x64():
        truth, template, space = blob_problem()
        stack = photos(truth, 1000, seed=11)
        return space, stack, fit_photos(space, template, stack)


@pytest.mark.slow
def test_monte_carlo_bias_below_0_1_stderr_and_coverage(monte_carlo):
    """Five free parameters (width, flux, background, centre), clipped core, 1000 draws:
    every parameter's bias below 0.1 of its standard error (the Monte-Carlo error of the
    mean is 0.032), and the 68 % and 95 % intervals (±1 and ±1.96 standard errors) cover
    the truth in 68 ± 5 % and 95 ± 3 % of the draws (binomial errors: 1.5 % and 0.7 %).
    Measured: biases -0.03 to 0.03, coverage 66.3-69.6 % and 94.2-95.6 %."""
    space, stack, fits = monte_carlo
    assert fits.converged.all()
    assert np.mean((stack >= SATURATION).sum(axis=(1, 2))) > 3
    for i, path in enumerate(space.paths):
        err = fits.values[:, i] - TRUTH[path]
        se = fits.stderr[:, i]
        assert np.all(np.isfinite(se)), path
        bias = err.mean() / se.mean()
        c68 = np.mean(np.abs(err) <= se)
        c95 = np.mean(np.abs(err) <= 1.959964 * se)
        print(f"{path}: bias {bias:+.3f} se, coverage {c68:.3f} / {c95:.3f}")
        assert abs(bias) < 0.1, (path, bias)
        assert 0.63 <= c68 <= 0.73, (path, c68)
        assert 0.92 <= c95 <= 0.98, (path, c95)


@pytest.mark.slow
def test_fit_ends_at_the_samplers_optimum(tmp_path):
    """`fit` on a photo of another seed: the sampler's log-probability at the result is
    within d/2 + 3 of the best of a short chain started there (d = 5; measured gap below
    0.1), the optimum check finds nothing to gain, and no flag is raised."""
    truth, template, space = blob_problem()
    target = photos(truth, 1, seed=23)[0]
    res = fit(space, template, target, n_starts=1, truth=TRUTH)
    assert res.converged, res.message
    assert "likelihood" in res.objective and res.covariance_scale == 1.0
    assert res.optimum_check["gain"] < 0.01 and res.optimum_check["decrement"] < 0.01
    assert res.flags == [], res.flags
    lp = make_log_posterior(space, template, target)
    at_fit = float(lp(space.to_latent(space.values_from(res.values))))
    post = sample(space, template, target, res, tmp_path / "chain.h5", n_walkers=16,
                  max_steps=200, until_converged=False, batch_size=16, progress=False,
                  seed=1)  # fmt: skip
    best = float(np.max(post.log_prob))
    print(f"log-probability at the fit {at_fit:.3f}, best in the chain {best:.3f}")
    assert at_fit >= best - (space.size / 2 + 3)


# --------------------------------------------------------------------------------------
# flags


def _flags(**overrides):
    base = dict(
        paths=["a", "b"], values={"a": 1.0, "b": 5.0}, stderr={"a": 0.1, "b": 0.5},
        bounds={"a": (0.0, 2.0, 1.0), "b": (0.0, math.inf, 4.0)}, truth=None,
        reduced_chi2=1.0, dof=1000, normalised=True, optimum=None, likelihood_pure=True,
    )  # fmt: skip
    return fit_flags(**{**base, **overrides})


def test_flags_truth_bounds_stderr_and_optimum():
    assert _flags() == []
    kinds = [f["kind"] for f in _flags(truth={"a": 1.35, "b": 5.5})]
    assert kinds == ["truth_beyond_3se"]  # 3.5 standard errors off; b is 1 off
    flags = _flags(values={"a": 1.995, "b": 0.03})
    assert [(f["kind"], f["path"]) for f in flags] == [("at_bound", "a"), ("at_bound", "b")]
    assert "upper bound 2" in flags[0]["message"] and "lower bound 0" in flags[1]["message"]
    assert [f["kind"] for f in _flags(stderr={"a": math.nan, "b": 0.5})] == ["stderr_undefined"]
    stalled = {"gain": 17.0, "decrement": 5.8, "steps": 3}
    (flag,) = _flags(optimum=stalled)
    assert flag["kind"] == "not_at_optimum" and "17" in flag["message"]
    assert "max_steps" in flag["message"]
    assert _flags(optimum={"gain": 0.4, "decrement": 0.3, "steps": 1}) == []
    # A reduced chi-square is judged against its own spread, and only when noise-normalised.
    assert _flags(reduced_chi2=1.04) == [] and _flags(reduced_chi2=3.0, normalised=False) == []
    (flag,) = _flags(reduced_chi2=1.5)
    assert flag["kind"] == "reduced_chi2" and flag["cause"] == "unknown"
    # The parameters' own flags alone (rerun when a fit's errors are replaced).
    args = (["a", "b"], {"a": 1.995, "b": 5.0}, {"a": 0.1, "b": 0.5})
    bounds = {"a": (0.0, 2.0, 1.0), "b": (0.0, math.inf, 4.0)}
    own = parameter_flags(*args, bounds, {"b": 7.0})
    assert [(f["kind"], f["path"]) for f in own] == [("at_bound", "a"), ("truth_beyond_3se", "b")]
    every = _flags(values=args[1], optimum=stalled, truth={"b": 7.0})
    assert own == [f for f in every if "path" in f] and every[0]["kind"] == "not_at_optimum"


def test_reduced_chi2_causes_are_told_apart():
    """White residuals too large where the photon noise dominates: the gain; where the read
    noise does: the read noise; correlated residuals: structure the model cannot draw;
    too small: the noise model overestimates."""
    rng = np.random.default_rng(0)
    n = 64
    y, x = np.mgrid[:n, :n]
    expected = 5.0 + 5e3 * np.exp(-((x - 32) ** 2 + (y - 32) ** 2) / (2 * 8.0**2))
    used = np.ones((n, n), bool)
    bright = expected / GAIN > READ**2
    white = rng.normal(size=(n, n))
    assert (
        chi2_cause(2.0, np.where(bright, 2.0, 1.0) * white, expected, used, GAIN, READ)[0]
        == "noise_gain"
    )
    assert (
        chi2_cause(2.0, np.where(bright, 1.0, 2.0) * white, expected, used, GAIN, READ)[0]
        == "noise_read"
    )
    lumpy = white + 2.0 * np.sin(x / 5.0) * np.cos(y / 7.0)
    cause, text = chi2_cause(3.0, lumpy, expected, used, GAIN, READ)
    assert cause == "model_misfit" and "cannot draw" in text
    assert chi2_cause(0.5, 0.7 * white, expected, used, GAIN, READ)[0] == "noise_overestimated"


def test_wrong_noise_model_and_misfit_are_flagged_in_a_fit():
    """Real fits (no clipping): a photo made with gain 0.5 fitted with gain 2 (the shot
    noise twice as large as assumed) is flagged with the gain as the cause; a blob with a
    faint companion two widths away, with structure the model cannot draw."""
    template = Forward(
        GaussPSF(2.0, 32), Observation(flux=1.5e5, background=40.0, gain=GAIN, read_noise=READ)
    )
    space = ParameterSpace(
        [Parameter("model.sigma_px", 1.0, 4.0, init=2.0)],
        nuisance=[
            Parameter("obs.flux", 0.0, math.inf, init=1.5e5),
            Parameter("obs.background", -50.0, 200.0, init=40.0),
        ],
    )
    noisy = Observation(flux=2e5, background=50.0, gain=0.5, read_noise=READ)
    res = fit(space, template, photos(noisy, 1, seed=31)[0], n_starts=1)
    (flag,) = [f for f in res.flags if f["kind"] == "reduced_chi2"]
    assert flag["cause"] == "noise_gain", flag
    blob = GaussPSF(SIGMA, 32)()
    pair = blob + 0.3 * jnp.roll(blob, 4, axis=1)
    clean = Observation(flux=2e5, background=50.0, gain=GAIN, read_noise=READ)
    target = np.asarray(clean.sample(jax.random.key(32), pair / pair.sum()))
    res = fit(space, template, target, n_starts=1)
    (flag,) = [f for f in res.flags if f["kind"] == "reduced_chi2"]
    assert flag["cause"] == "model_misfit", flag


@pytest.mark.slow
def test_stalled_fit_is_flagged_and_the_report_leads_with_the_flags(tmp_path):
    """Two solver steps from a poor start: not at the optimum (the check's scoring steps gain
    far more than d/2), and the truth is many standard errors away; `params.json` carries
    the flags and `report.md` opens with them."""
    truth, template, space = blob_problem()
    target = photos(truth, 1, seed=41)[0]
    res = fit(space, template, target, n_starts=1, max_steps=2, truth=TRUTH)
    kinds = [f["kind"] for f in res.flags]
    assert kinds[0] == "not_at_optimum" and "truth_beyond_3se" in kinds, kinds
    assert res.optimum_check["gain"] > space.size / 2
    info = ReportInfo(name="stalled", target=target, pixel_scale_deg=0.01, saturation=SATURATION)
    out = write_report(tmp_path / "stalled", res, info)
    params = json.loads((out / "params.json").read_text())
    assert [f["kind"] for f in params["flags"]] == kinds
    assert params["objective"].startswith("the Poisson–Gaussian likelihood")
    text = (out / "report.md").read_text()
    head = text.split("## Result")[0]
    assert "flags — when to distrust this fit" in head and "**not_at_optimum**" in head
    assert "- **Maximised:** the Poisson–Gaussian likelihood" in head
    again = FitResult.from_json(out / "params.json")
    assert again.flags == res.flags and again.objective == res.objective
