"""Posterior sampling: the plumbing against an analytic posterior, checkpoints, starts, bad input,
and a glare-model posterior whose intervals cover the truth at the stated rate.

Float64 throughout. The fast tests use a linear-Gaussian toy that runs through the
same code path as a real fit (Forward + Observation + ParameterSpace + emcee); the
glare-model tests fit a 64-px photo of a disk pupil.
"""

import json
import math
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import x64
from jaxtyping import Array, Float

from invglare.aperture import Aperture, Disk
from invglare.errors import ConfigError, InputDataError, NumericalError
from invglare.fit import FitResult, Forward, Observation, Parameter, ParameterSpace, fit
from invglare.fit.posterior_report import write_posterior_report
from invglare.fit.sample import (
    BatchedLogProb,
    SampleProgress,
    check_priors,
    initial_walkers,
    load_chain,
    make_log_posterior,
    parse_moves,
    sample,
    tune_batch_size,
)
from invglare.models.aperture_psf import AperturePSF

DIAMETER = "model.inner.aperture.shapes[0].diameter_mm"


@pytest.fixture(autouse=True)
def _float64():
    with x64():
        yield


# --------------------------------------------------------------------------------------
# the linear-Gaussian toy


class FixedPSF(eqx.Module):
    """A fixed unit-energy PSF: the photo is then linear in flux and background."""

    psf: Float[Array, "h w"]
    log_scale: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=1.0)

    def __call__(self):
        # log_scale is 1 except in the NaN test, where a negative value gives NaN.
        return self.psf * jnp.log(self.log_scale * math.e)


N_TOY = 16
SIGMA = 5.0  # read noise, counts; gain ~inf makes the noise Gaussian with constant variance
PRIOR_FLUX = (350.0, 100.0)


def toy_psf():
    y, x = np.mgrid[:N_TOY, :N_TOY]
    g = np.exp(-((x - N_TOY // 2) ** 2 + (y - N_TOY // 2) ** 2) / (2 * 1.5**2))
    return g / g.sum()


def toy_problem(seed=0):
    """Photo = flux * g + background + N(0, SIGMA²); normal prior on flux, flat on background.

    Flux has a log transform (0, inf) and background a logit one (-1000, 1000), so both
    latent Jacobians are exercised; the bounds are > 30 sigma away (no truncation).
    """
    g = toy_psf()
    obs = Observation(flux=400.0, background=10.0, gain=1e12, read_noise=SIGMA)
    fwd = Forward(FixedPSF(jnp.asarray(g)), obs)
    rng = np.random.default_rng(seed)
    target = np.asarray(obs.expected(jnp.asarray(g))) + SIGMA * rng.standard_normal(g.shape)
    space = ParameterSpace(
        [Parameter("obs.flux", 0.0, math.inf, init=300.0, prior=("normal", *PRIOR_FLUX))],
        nuisance=[Parameter("obs.background", -1000.0, 1000.0, init=5.0)],
    )
    return space, fwd, target


def toy_analytic(target):
    """Exact Gaussian posterior of (flux, background): precision A^T A / s² + prior."""
    g = toy_psf()
    a = np.column_stack([g.ravel(), np.ones(g.size)])
    prec = a.T @ a / SIGMA**2 + np.diag([1 / PRIOR_FLUX[1] ** 2, 0.0])
    rhs = a.T @ target.ravel() / SIGMA**2 + np.array([PRIOR_FLUX[0] / PRIOR_FLUX[1] ** 2, 0.0])
    cov = np.linalg.inv(prec)
    return cov @ rhs, cov


def toy_fit_result(space, mean, cov, converged=True, paths=None):
    """A FitResult at the analytic optimum (the toy needs no optimiser)."""
    paths = list(space.paths) if paths is None else paths
    return FitResult(
        paths=paths,
        values=dict(zip(paths, map(float, mean), strict=True)),
        stderr=dict(zip(paths, map(float, np.sqrt(np.diag(cov))), strict=True)),
        covariance=np.asarray(cov),
        nuisance=[paths[-1]],
        converged=converged,
        message="converged after 3 steps" if converged else "hit max_steps=2 without converging",
    )


@pytest.fixture(scope="module")
def toy():
    with x64():
        space, fwd, target = toy_problem()
        mean, cov = toy_analytic(target)
        yield space, fwd, target, mean, cov, toy_fit_result(space, mean, cov)


@pytest.fixture(scope="module")
def toy_chain(toy, tmp_path_factory):
    """The toy posterior, 64 walkers x 500 steps, with the truth known to the report."""
    space, fwd, target, mean, cov, res = toy
    res = toy_fit_result(space, mean, cov)
    res.truth = {"obs.flux": 400.0, "obs.background": 10.0}
    with x64():
        return sample(
            space, fwd, target, res, tmp_path_factory.mktemp("toy") / "chain.h5", n_walkers=64,
            max_steps=500, until_converged=False, batch_size=32, progress=False, seed=3,
        )  # fmt: skip


def test_toy_posterior_mean_and_covariance_match_analytic(toy, toy_chain):
    """Mean within 0.15 sd, sds within 10 %, correlation within 0.1 of the exact posterior.

    64 walkers x 500 steps, tau ~ 30: ~900 effective samples, so the standard errors
    are ~0.03 sd (mean), ~2.5 % (sd) and ~0.03 (correlation); the tolerances are ~4-5
    of them.
    """
    space, _fwd, _target, mean, cov, _res = toy
    post = toy_chain
    s = post.samples()
    sd = np.sqrt(np.diag(cov))
    np.testing.assert_array_less(np.abs(s.mean(axis=0) - mean) / sd, 0.15)
    np.testing.assert_allclose(s.std(axis=0), sd, rtol=0.10)
    rho = cov[0, 1] / (sd[0] * sd[1])
    assert abs(post.correlation()[0, 1] - rho) < 0.1
    # The prior matters here (it pulls the flux by ~1 sd from the likelihood's optimum):
    # the posterior is not just the likelihood.
    assert post.n_steps == 500 and post.chain.shape == (500, 64, 2)
    assert post.sampling_space == "latent"
    # Stored physical values are the transforms of the latent chain.
    np.testing.assert_allclose(
        post.chain, np.asarray(space.from_latent(jnp.asarray(post.latent))), rtol=1e-12
    )
    assert 0.2 < post.acceptance.mean() < 0.85
    assert all(5 < t < 100 for t in post.tau.values())


def test_log_posterior_is_likelihood_plus_prior_plus_jacobian(toy):
    space, fwd, target, mean, _cov, _ = toy
    lp = make_log_posterior(space, fwd, target)
    z = space.to_latent(jnp.asarray(mean + np.array([10.0, -0.2])))
    x = space.from_latent(z)
    f = space.apply(fwd, x)
    expected_ll = float(f.obs.log_likelihood(jnp.asarray(target), f.expected()))
    # Independent Gaussian log-likelihood, written out.
    e = np.asarray(f.expected())
    ll = -0.5 * np.sum((target - e) ** 2 / SIGMA**2 + np.log(2 * np.pi * SIGMA**2))
    np.testing.assert_allclose(expected_ll, ll, rtol=1e-9)
    total = ll + float(space.log_prior(x)) + float(space.log_det_jacobian(z))
    np.testing.assert_allclose(float(lp(z)), total, rtol=1e-12)
    # The batched evaluator returns the same, plus the physical values as blobs.
    out = BatchedLogProb(lp, 2)(np.asarray(jnp.stack([z, z, z])))
    assert out.shape == (3, 3)
    np.testing.assert_allclose(out[:, 0], total, rtol=1e-12)
    np.testing.assert_allclose(out[:, 1:], np.asarray(x)[None].repeat(3, 0), rtol=1e-12)


def test_batch_sizes_give_identical_values_and_tuning_reports_each(toy):
    space, fwd, target, _mean, _cov, res = toy
    lp = make_log_posterior(space, fwd, target)
    walkers = initial_walkers(space, res, 10, log_prob=BatchedLogProb(lp, 4), seed=1)
    ref = BatchedLogProb(lp, 1).evaluate(walkers)[0]
    for b in (3, 10):  # 3 does not divide 10: the last batch is padded
        np.testing.assert_allclose(BatchedLogProb(lp, b).evaluate(walkers)[0], ref, rtol=1e-12)
    # Programs are shared between evaluators: tuning reuses the ones compiled above.
    best, table = tune_batch_size(lp, walkers, [1, 4], repeats=1)
    assert set(table) == {1, 4} and best in table and all(t > 0 for t in table.values())


# --------------------------------------------------------------------------------------
# resume


def _stored(path):
    return load_chain(path)


def test_interrupted_run_resumes_to_the_requested_length_keeping_stored_steps(toy, tmp_path):
    """Ctrl-C (KeyboardInterrupt from the progress callback) after 120 of 300 steps, resume.

    The resumed chain has 300 steps, its first 120 are the ones stored before the
    interrupt, and (random state restored) it equals an uninterrupted run.
    """
    space, fwd, target, _mean, _cov, res = toy
    kw = dict(n_walkers=8, max_steps=300, until_converged=False, batch_size=8, seed=5)
    path = tmp_path / "chain.h5"
    seen = []

    def stop(p: SampleProgress):
        seen.append(p.iteration)
        if p.iteration == 120:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        sample(space, fwd, target, res, path, progress=stop, **kw)
    assert seen[-1] == 120
    before = _stored(path)
    assert before.n_steps == 120
    assert before.runs[-1]["stopped"] == "interrupted"
    # Without resume (or restart) an existing chain is not overwritten.
    with pytest.raises(ConfigError, match="already holds a chain of 120 steps"):
        sample(space, fwd, target, res, path, progress=False, **kw)
    after = sample(space, fwd, target, res, path, progress=False, resume=True, **kw)
    assert after.n_steps == 300
    np.testing.assert_array_equal(after.latent[:120], before.latent)
    np.testing.assert_array_equal(after.log_prob[:120], before.log_prob)
    full = sample(space, fwd, target, res, tmp_path / "full.h5", progress=False, **kw)
    np.testing.assert_array_equal(after.latent, full.latent)
    assert [r["start_step"] for r in after.runs] == [0, 120]


def test_an_interrupt_inside_hdf5_is_still_recorded_as_interrupted(toy, tmp_path):
    """A signal that lands while h5py holds the chain open (in emcee's write, or a read)
    leaves that file id alive in the interrupted frame. The run must still record itself
    "interrupted" with its committed steps, not fail re-opening the file with other flags."""
    import h5py

    space, fwd, target, _mean, _cov, res = toy
    path = tmp_path / "chain.h5"

    def stop(p: SampleProgress):
        if p.iteration == 30:
            held = h5py.h5f.open(str(path).encode(), h5py.h5f.ACC_RDONLY)  # noqa: F841
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        sample(space, fwd, target, res, path, progress=stop, n_walkers=8, max_steps=100,
               until_converged=False, batch_size=8, seed=5)  # fmt: skip
    stored = _stored(path)
    assert stored.n_steps == 30
    assert stored.runs[-1]["stopped"] == "interrupted"
    assert stored.runs[-1]["end_step"] == 30


def test_resume_refuses_missing_chain_other_parameters_and_walker_change(toy, tmp_path):
    space, fwd, target, _mean, _cov, res = toy
    path = tmp_path / "chain.h5"
    kw = dict(until_converged=False, batch_size=8, progress=False)
    with pytest.raises(InputDataError, match="no chain to resume"):
        sample(space, fwd, target, res, path, resume=True, max_steps=5, **kw)
    sample(space, fwd, target, res, path, n_walkers=8, max_steps=5, **kw)
    with pytest.raises(ConfigError, match="keeps its walkers"):
        sample(space, fwd, target, res, path, n_walkers=10, resume=True, max_steps=8, **kw)
    with pytest.raises(InputDataError, match="another photo"):
        sample(space, fwd, target + 1.0, res, path, resume=True, max_steps=8, **kw)
    other = ParameterSpace(
        [Parameter("obs.flux", 0.0, math.inf, init=300.0)],
        nuisance=[Parameter("obs.read_noise", 0.0, 100.0, init=5.0)],
    )
    res2 = toy_fit_result(other, [400.0, 5.0], np.diag([100.0, 0.1]))
    with pytest.raises(InputDataError, match="another model or config"):
        sample(other, fwd, target, res2, path, resume=True, max_steps=8, **kw)
    with pytest.raises(InputDataError, match="another model or config"):
        load_chain(path, other)
    # A restart replaces the chain.
    post = sample(space, fwd, target, res, path, n_walkers=10, restart=True, max_steps=4, **kw)
    assert post.n_walkers == 10 and post.n_steps == 4


@pytest.mark.slow
def test_killed_process_resumes_without_losing_stored_steps(tmp_path):
    """A subprocess sampling the toy is sent SIGTERM (a plain `kill`) mid-run.

    Every step counted in the file before the kill is intact and reproduced by the
    resumed run, which reaches the requested length.
    """
    path = tmp_path / "chain.h5"
    script = textwrap.dedent(
        f"""
        import sys
        sys.path[:0] = [{str(Path(__file__).parent)!r}, {str(Path(__file__).parents[1])!r}]
        import jax
        jax.config.update("jax_enable_x64", True)
        from test_sample import toy_problem, toy_analytic, toy_fit_result
        from invglare.fit.sample import sample
        space, fwd, target = toy_problem()
        mean, cov = toy_analytic(target)
        res = toy_fit_result(space, mean, cov)
        sample(space, fwd, target, res, {str(path)!r}, n_walkers=8, max_steps=100000,
               until_converged=False, batch_size=8, progress=False, seed=7)
        """
    )
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    proc = subprocess.Popen([sys.executable, "-c", script], env=env)
    try:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            time.sleep(0.5)
            if path.is_file():
                try:
                    if load_chain(path).n_steps >= 150:
                        break
                except InputDataError:
                    pass  # not initialised yet
            assert proc.poll() is None, "the sampling subprocess ended early"
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    before = load_chain(path)
    assert before.n_steps >= 150
    assert before.runs[-1]["stopped"] == "interrupted"
    space, fwd, target = toy_problem()
    mean, cov = toy_analytic(target)
    res = toy_fit_result(space, mean, cov)
    total = before.n_steps + 40
    after = sample(
        space, fwd, target, res, path, resume=True, max_steps=total, until_converged=False,
        batch_size=8, progress=False,
    )  # fmt: skip
    assert after.n_steps == total
    np.testing.assert_array_equal(after.latent[: before.n_steps], before.latent)


# --------------------------------------------------------------------------------------
# starts and refusals


def test_initial_walkers_lie_inside_bounds_even_when_the_covariance_is_wide():
    """A fit near its bounds with a covariance much wider than them: every walker inside."""
    space = ParameterSpace(
        [
            Parameter("obs.flux", 0.0, 10.0, init=1.0),  # logit
            Parameter("obs.background", -1.0, 1.0, init=0.0, transform="identity"),
        ]
    )
    res = toy_fit_result(space, [9.9, 0.98], np.diag([25.0, 4.0]))
    walkers = initial_walkers(space, res, 40, scale=1.0, seed=2)
    x = np.asarray(space.from_latent(jnp.asarray(walkers)))
    assert np.all((x[:, 0] > 0) & (x[:, 0] < 10))
    assert np.all((x[:, 1] >= -1) & (x[:, 1] <= 1))
    assert len(np.unique(walkers[:, 0])) == 40  # a ball, not copies of the fit
    # A fit value on its bound: refused, or (forced) started just inside.
    on_bound = toy_fit_result(space, [10.0, 0.0], np.diag([np.nan, 0.01]))
    with pytest.raises(InputDataError, match=r"fit value 10 of 'obs.flux' is on .*\[0, 10\]"):
        initial_walkers(space, on_bound, 8)
    w = np.asarray(space.from_latent(jnp.asarray(initial_walkers(space, on_bound, 8, force=True))))
    assert np.all((w[:, 0] > 9.9) & (w[:, 0] < 10.0))
    # A NaN covariance entry (an unconstrained parameter) still gives a spread.
    res_nan = toy_fit_result(space, [5.0, 0.0], np.array([[np.nan, np.nan], [np.nan, 0.01]]))
    w = initial_walkers(space, res_nan, 8, seed=1)
    assert np.all(np.std(w, axis=0) > 0)


def test_refuses_a_fit_that_did_not_converge_unless_forced(toy, tmp_path):
    space, fwd, target, mean, cov, _ = toy
    bad = toy_fit_result(space, mean, cov, converged=False)
    with pytest.raises(NumericalError, match=r"did not converge .*max_steps.*force"):
        sample(space, fwd, target, bad, tmp_path / "c.h5", n_walkers=8, max_steps=3,
               batch_size=8, progress=False)  # fmt: skip
    assert not (tmp_path / "c.h5").exists()
    post = sample(space, fwd, target, bad, tmp_path / "c.h5", n_walkers=8, max_steps=3,
                  batch_size=8, progress=False, force=True, until_converged=False)  # fmt: skip
    assert post.n_steps == 3


def test_bad_input_errors_name_the_problem(toy, tmp_path):
    space, fwd, target, mean, cov, res = toy
    kw = dict(n_walkers=8, max_steps=3, batch_size=8, progress=False)
    # A fit result of another model.
    other = toy_fit_result(space, mean, cov, paths=["model.sigma_px", "obs.background"])
    with pytest.raises(InputDataError, match=r"\['model.sigma_px'.*another model"):
        sample(space, fwd, target, other, tmp_path / "a.h5", **kw)
    # A missing fit result file.
    with pytest.raises(InputDataError, match="does not exist"):
        FitResult.from_json(tmp_path / "missing" / "params.json")
    # A prior with no mass inside the bounds.
    zero = ParameterSpace([Parameter("obs.flux", 0.0, 1000.0, 300.0, ("normal", 1e5, 10.0))])
    with pytest.raises(ConfigError, match=r"'obs.flux' puts 0.0e\+00 .*\[0, 1000\]"):
        check_priors(zero)
    neg = ParameterSpace([Parameter("obs.background", -10.0, -1.0, -5.0, ("lognormal", 0, 1))])
    with pytest.raises(ConfigError, match="lognormal"):
        make_log_posterior(neg, fwd, target)
    # Too few or odd walkers; unknown moves.
    with pytest.raises(ConfigError, match="even integer >= 2 x 2"):
        initial_walkers(space, res, 3)
    with pytest.raises(ConfigError, match="unknown move 'metropolis'"):
        parse_moves("metropolis")
    with pytest.raises(ConfigError, match="must be finite and > 0"):
        parse_moves({"de": -1.0})
    assert parse_moves({"de": 0.8, "de_snooker": 0.2}) == [("de", 0.8), ("de_snooker", 0.2)]


def test_nan_log_probability_at_the_start_is_a_clear_error(tmp_path):
    g = toy_psf()
    fwd = Forward(FixedPSF(jnp.asarray(g)), Observation(flux=400.0, gain=1e12, read_noise=SIGMA))
    target = 400.0 * g + SIGMA * np.random.default_rng(0).standard_normal(g.shape)
    space = ParameterSpace(
        [Parameter("model.log_scale", -10.0, 10.0, init=1.0, transform="identity")],
        nuisance=[Parameter("obs.flux", 0.0, math.inf, init=400.0)],
    )
    # log(negative) inside the bounds: the model gives NaN at the fit value.
    res = toy_fit_result(space, [-1.0, 400.0], np.diag([0.01, 100.0]))
    with pytest.raises(NumericalError, match=r"log-probability at the fit optimum .* is NaN"):
        sample(space, fwd, target, res, tmp_path / "n.h5", n_walkers=8, max_steps=3,
               batch_size=8, progress=False)  # fmt: skip


def test_moves_are_selectable_and_recorded(toy, tmp_path):
    space, fwd, target, _mean, _cov, res = toy
    post = sample(
        space, fwd, target, res, tmp_path / "m.h5", n_walkers=8, max_steps=20,
        moves={"de": 0.8, "de_snooker": 0.2}, until_converged=False, batch_size=4,
        progress=False,
    )  # fmt: skip
    assert post.moves == [("de", 0.8), ("de_snooker", 0.2)]
    assert post.runs[0]["moves"] == [["de", 0.8], ["de_snooker", 0.2]]
    # A short chain is flagged with what to do.
    assert any("shorter than 50 autocorrelation times" in w and "--resume" in w
               for w in post.warnings)  # fmt: skip


def test_digits_resolve_the_interval():
    """A narrow posterior keeps its digits: 37 +- 1e-4 is not '37 | 37 | 37'."""
    from invglare.fit.posterior_report import digits_to_resolve

    n = digits_to_resolve(37.000012, 36.99990, 37.00011)
    assert n == 8 and len({f"{v:.{n}g}" for v in (37.000012, 36.9999, 37.00011)}) == 3
    assert digits_to_resolve(2.8, 2.7, 2.9) == 5  # at least five, as before
    assert digits_to_resolve(0.0, -1.0, 1.0) == 5 and digits_to_resolve(3.0, 3.0, 3.0) == 5


def test_report_files_are_written_with_the_summary_numbers(toy, toy_chain, tmp_path):
    space, fwd, target, _mean, _cov, _res = toy
    post = toy_chain
    files = write_posterior_report(post, tmp_path / "posterior", space=space,
                                   forward_template=fwd, target=target, name="toy",
                                   n_predictive=16)  # fmt: skip
    assert set(files) == {"corner", "trace", "predictive", "json", "markdown"}
    for f in files.values():
        assert f.stat().st_size > 0
    summary = json.loads(files["json"].read_text())
    pc = post.percentiles()
    e = summary["parameters"]["obs.flux"]
    assert e["median"] == pytest.approx(pc["obs.flux"]["median"])
    assert e["p2_5"] < e["p16"] < e["median"] < e["p84"] < e["p97_5"]
    assert e["truth"] == 400.0 and "tau" in e
    assert e["truth_in_95"] == (e["p2_5"] <= 400.0 <= e["p97_5"])
    assert summary["moves"] == [["stretch", 1.0]]
    md = files["markdown"].read_text()
    assert "| `obs.flux` |" in md and "corner.png" in md and "predictive.png" in md
    # Every row's percentiles are written apart: enough digits for its interval.
    for row in (line for line in md.splitlines() if line.startswith("| `")):
        cells = [c.strip() for c in row.split("|")[2:7]]
        assert len(set(cells)) == 5, row
    assert 0.5 < summary["predictive"]["fraction_of_rings_inside_95"] <= 1.0
    assert not list((tmp_path / "posterior").glob(".*tmp*"))  # atomic: no temporary litter


# --------------------------------------------------------------------------------------
# a glare-model posterior


class CollectingPupil(eqx.Module):
    """A pupil's PSF times the light it collects, ``(D / D_ref)²``.

    The PSF of :class:`AperturePSF` has unit energy whatever the pupil; a photo of a
    point source through a pupil of diameter D holds ``flux * (D / D_ref)²`` counts,
    which is where the flux-diameter trade-off of a real photo comes from.
    """

    inner: AperturePSF
    reference_mm: float = eqx.field(static=True, default=3.0)

    def __call__(self):
        d = self.inner.aperture.shapes[0].diameter_mm
        return self.inner() * (d / self.reference_mm) ** 2


TRUE_D, TRUE_FLUX = 3.0, 2e5


def glare_photo(seed):
    """A 64-px photo of a 3 mm disk pupil (Airy core ~3 px), Poisson-Gaussian noise."""
    inner = AperturePSF.build(
        Aperture((Disk(TRUE_D),)), focal_length_mm=17.0, npix=64, pixel_scale_deg=0.0035,
        aperture_npix=64, window_mm=5.4,
    )  # fmt: skip
    obs = Observation(flux=TRUE_FLUX, background=20.0, gain=2.0, read_noise=3.0)
    model = CollectingPupil(inner)
    target = np.asarray(obs.sample(jax.random.key(seed), model()))
    template = Forward(
        eqx.tree_at(lambda m: m.inner.aperture.shapes[0].diameter_mm, model, jnp.asarray(3.3)),
        Observation(flux=1.5e5, background=20.0, gain=2.0, read_noise=3.0),
    )
    space = ParameterSpace(
        [Parameter(DIAMETER, 2.0, 5.0, init=3.3)],
        nuisance=[Parameter("obs.flux", 0.0, math.inf, init=1.5e5)],
    )
    return space, template, target


def fit_and_sample(seed, path, steps, walkers=8):
    space, template, target = glare_photo(seed)
    truth = {DIAMETER: TRUE_D, "obs.flux": TRUE_FLUX}
    res = fit(space, template, target, {"pixels": 1.0}, starts=[[3.3, 1.5e5]],
              covariance_scale="absolute", truth=truth)  # fmt: skip
    post = sample(space, template, target, res, path, n_walkers=walkers, max_steps=steps,
                  until_converged=False, batch_size=8, progress=False, seed=seed)  # fmt: skip
    return space, template, target, res, post


@pytest.mark.slow
def test_glare_posterior_covers_truth_and_shows_flux_diameter_correlation(tmp_path):
    """One photo: the 95 % intervals hold the truth; flux and diameter anti-correlate; the
    posterior's widths and correlation are the fit's (Laplace) ones.

    The photo pins ``flux * D²`` (the counts) better than D alone, so the correlation
    is about -0.5 (Fisher information at the truth: -0.49). The posterior is Gaussian to
    0.1 %: its standard deviations, integrated on a 61² grid of ±6 standard errors, are
    0.9991 and 0.99994 of the fit's. So the chain's may differ from the fit's by its Monte
    Carlo error alone: 32 walkers x 1500 steps, tau 28-30, give ~1600 effective samples, a
    standard deviation to ~1.8 % and the correlation to ~0.019; the tolerances, 6 % and
    0.05, are about 3.4 and 2.6 of those (measured: 2.5 % and 2.8 %, 0.004).
    """
    space, _template, _target, res, post = fit_and_sample(11, tmp_path / "chain.h5", 1500, 32)
    assert min(post.effective_samples().values()) > 1000
    pc = post.percentiles()
    for p, t in ((DIAMETER, TRUE_D), ("obs.flux", TRUE_FLUX)):
        assert pc[p]["p2_5"] <= t <= pc[p]["p97_5"], (p, pc[p], t)
    rho = post.correlation()[0, 1]
    c = res.covariance
    rho_fit = c[0, 1] / math.sqrt(c[0, 0] * c[1, 1])
    assert rho < -0.3 and abs(rho - rho_fit) < 0.05, (rho, rho_fit)
    for i, p in enumerate(space.paths):
        assert post.samples()[:, i].std() == pytest.approx(res.stderr[p], rel=0.06)


@pytest.mark.slow
def test_glare_interval_coverage_over_noise_draws(tmp_path):
    """Over 10 noise draws x 2 parameters, 95 % intervals cover the truth >= 17 of 20
    times and 68 % intervals 9-19 of 20 (binomial: each bound is violated with
    probability < 2 % for calibrated intervals; 20 of 20 at 68 % would mean intervals
    far too wide)."""
    in95 = in68 = 0
    for seed in range(10):
        _space, _, _, _, post = fit_and_sample(100 + seed, tmp_path / f"c{seed}.h5", 500)
        pc = post.percentiles()
        for p, t in ((DIAMETER, TRUE_D), ("obs.flux", TRUE_FLUX)):
            in95 += pc[p]["p2_5"] <= t <= pc[p]["p97_5"]
            in68 += pc[p]["p16"] <= t <= pc[p]["p84"]
    print(f"coverage: 95% intervals {in95}/20, 68% intervals {in68}/20")
    assert in95 >= 17
    assert 9 <= in68 <= 19


# --------------------------------------------------------------------------------------
# the command


def test_sample_section_is_checked(tmp_path):
    from invglare.config.sample import read_sample_section

    cfg = tmp_path / "fit.toml"
    cfg.write_text("[sample]\nwalkers = 16\nmoves = {de = 0.8, de_snooker = 0.2}\n")
    opts = read_sample_section(cfg)
    assert opts["walkers"] == 16 and opts["moves"] == {"de": 0.8, "de_snooker": 0.2}
    assert opts["steps"] == 5000 and opts["batch_size"] == "auto"
    cfg.write_text("[sample]\nwalker = 16\n")
    with pytest.raises(ConfigError, match="unknown key 'walker'"):
        read_sample_section(cfg)
    cfg.write_text('[sample]\nmoves = "gibbs"\n')
    with pytest.raises(ConfigError, match="unknown move 'gibbs'"):
        read_sample_section(cfg)


def test_a_reference_fit_is_refused_with_the_reason():
    """The bundled CIE regression fit has no photo and no noise model: `invglare sample`
    says so (exit 2, one line) instead of reporting an unknown [reference] section."""
    from typer.testing import CliRunner

    from invglare.cli import app

    config = Path(__file__).resolve().parents[2] / "fits" / "cie_A50_p1.toml"
    result = CliRunner().invoke(app, ["sample", str(config)])
    assert result.exit_code == 2
    assert "reference glare function" in result.output
    assert "no likelihood to sample" in result.output
    assert "unknown section" not in result.output
