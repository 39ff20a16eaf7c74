"""Batch fitting without a cluster: shared compiled solves, vmapped photos, the batch table.

The Dask runs themselves (a real LocalCluster, worker deaths, resumes) are in
tests/commands/test_fit_batch.py; here the pieces they rest on are checked on a cheap
Gaussian-PSF problem: photos of one config share one compiled solve (the residual function
holds no photo-specific static value), ``fit_many`` / ``fit_staged_many`` give each photo
the answer of its own fit, and the table and figures say what the results say.
"""

import csv
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import x64
from jaxtyping import Array, Float

from invglare.errors import ConfigError
from invglare.files.toml import load_toml
from invglare.fit import FitResult, Forward, Observation, Parameter, ParameterSpace, fit
from invglare.fit.batch import (
    Outcome,
    Task,
    check_address,
    dask_client,
    finished,
    recover_unfinished,
)
from invglare.fit.batch_figures import population_figures
from invglare.fit.batch_table import collect_rows, recovery, short_names, to_csv, to_markdown
from invglare.fit.solve import fit_many, stack_modules
from invglare.fit.stages import Stage, fit_staged, fit_staged_many
from invglare.fit.views import make_residual_fn

SIGMA = "model.sigma_px"


class GaussPSF(eqx.Module):
    """A unit-energy Gaussian PSF on a 32-px grid."""

    sigma_px: Float[Array, ""] = eqx.field(converter=jnp.asarray)
    npix: int = eqx.field(static=True, default=32)

    def __call__(self):
        c = self.npix // 2
        x = jnp.arange(self.npix, dtype=self.sigma_px.dtype) - c
        g = jnp.exp(-(x[None, :] ** 2 + x[:, None] ** 2) / (2 * self.sigma_px**2))
        return g / jnp.sum(g)


def photo(sigma: float, flux: float, seed: int, npix: int = 32):
    """A Gaussian photo with noise, and the fit's space and template guessed from it (as
    ``load_fit`` does: flux and background start from the photo, so inits differ)."""
    truth = Observation(flux=flux, background=10.0, dx_px=0.2, read_noise=2.0)
    target = np.asarray(truth.sample(jax.random.key(seed), GaussPSF(sigma, npix)()))
    obs = Observation.from_target(target, read_noise=2.0)
    space = ParameterSpace(
        [Parameter(SIGMA, 1.0, 5.0, init=3.0)],
        nuisance=[
            Parameter("obs.flux", 0.0, math.inf, init=float(obs.flux)),
            Parameter("obs.background", -50.0, 500.0, init=float(obs.background)),
            Parameter("obs.dx_px", -2.0, 2.0, init=0.0),
        ],
    )
    truth_values = {SIGMA: sigma, "obs.flux": flux, "obs.background": 10.0, "obs.dx_px": 0.2}
    return space, Forward(GaussPSF(3.0, npix), obs), target, truth_values


@pytest.fixture(autouse=True)
def _float64():
    with x64():
        yield


@pytest.fixture(scope="module")
def photos():
    with x64():
        return [photo(2.0, 4e4, 1), photo(2.6, 6e4, 2), photo(3.1, 5e4, 3)]


def starts_of(space, sigmas=(1.8, 3.6)):
    init = np.asarray([p.init for p in space.all])
    return np.stack([np.concatenate([[s], init[1:]]) for s in sigmas])


def test_residual_functions_of_two_photos_share_their_static_part(photos):
    """The photos' guesses (flux, background) differ, so their spaces differ; the residual
    functions, which hold the space's structure, do not, and neither do the radial view's
    noise floors (leaves)."""
    (s1, f1, t1, _), (s2, f2, t2, _) = photos[:2]
    assert s1 != s2
    assert s1.structure() == s2.structure()
    assert [p.lower for p in s1.structure().all] == [p.lower for p in s1.all]
    views = {"pixels": 1.0, "radial": 0.5, "log": 0.1}
    fn1, fn2 = (make_residual_fn(s, f, t, views) for s, f, t in ((s1, f1, t1), (s2, f2, t2)))
    d1, st1 = eqx.partition(fn1, eqx.is_array)
    d2, st2 = eqx.partition(fn2, eqx.is_array)
    assert jax.tree_util.tree_structure(d1) == jax.tree_util.tree_structure(d2)
    assert st1 == st2
    assert float(fn1.views[1].floor) != float(fn2.views[1].floor)  # photo-specific, as leaves


@pytest.mark.slow
def test_second_photo_reuses_the_compiled_solve_and_its_answer_is_unchanged(photos):
    """A second photo of the same structure compiles nothing; its result is the one a
    fresh process would get (the solve does not read the space's inits)."""
    (s1, f1, t1, _), (s2, f2, t2, _) = photos[:2]
    kw = {"max_steps": 60, "batch": "loop"}
    first = fit(s1, f1, t1, starts=starts_of(s1), **kw)
    second = fit(s2, f2, t2, starts=starts_of(s2), **kw)
    assert second.timing_s["compile"] == 0.0
    assert first.converged and second.converged
    assert abs(second.values[SIGMA] - 2.6) < 0.05


@pytest.mark.slow
def test_fit_many_gives_each_photo_its_own_fit(photos):
    """Three photos in one vmapped solve per stage, vmapped starts and looped starts, equal
    their separate fits to 1e-8 relative (measured: 1e-11 at most). The step counts may
    differ: at the end the loss is flat to rounding, and when the stopping test trips there
    depends on the last bits, which batched arithmetic rounds differently."""
    for batch in ("vmap", "loop"):
        kw = {"max_steps": 80, "batch": batch, "coarse_to_fine": (2, 1), "refine_top": 2}
        alone = [
            fit(s, f, t, starts=starts_of(s), truth={SIGMA: tv[SIGMA]}, **kw)
            for s, f, t, tv in photos
        ]
        together = fit_many(
            [p[0] for p in photos], [p[1] for p in photos], [p[2] for p in photos],
            starts=[starts_of(p[0]) for p in photos],
            truths=[{SIGMA: p[3][SIGMA]} for p in photos], **kw,
        )  # fmt: skip
        for a, b in zip(alone, together, strict=True):
            assert b.converged == a.converged, batch
            for path in a.paths:
                np.testing.assert_allclose(b.values[path], a.values[path], rtol=1e-8)
                np.testing.assert_allclose(b.stderr[path], a.stderr[path], rtol=1e-6)
            assert b.truth == a.truth
            assert len(b.stages) == 2 and b.stages[0]["factor"] == 2


@pytest.mark.parametrize("branch", [(), ((SIGMA, (0, 1)),)], ids=["one", "branched"])
@pytest.mark.slow
def test_fit_staged_many_equals_fit_staged_with_a_scan_and_a_held_stage(photos, branch):
    stage = Stage({"radial": 1.0}, 30, ("obs.dx_px",), branch)
    alone, per_photo = [], []
    for s, f, t, tv in photos:
        scan_points = starts_of(s, np.linspace(1.2, 4.8, 9))
        truth = {SIGMA: tv[SIGMA]}
        per_photo.append(
            {"space": s, "forward": f, "target": t, "views": {"pixels": 1.0},
             "starts": starts_of(s), "scan_points": scan_points, "truth": truth}
        )  # fmt: skip
        alone.append(
            fit_staged(s, f, t, {"pixels": 1.0}, starts_of(s), stages=[stage],
                       scan_points=scan_points, truth=truth, max_steps=60)
        )  # fmt: skip
    together = fit_staged_many(per_photo, stages=[stage], max_steps=60)
    for a, b in zip(alone, together, strict=True):
        for path in a.paths:
            np.testing.assert_allclose(b.values[path], a.values[path], rtol=1e-8)
        assert [st["views"] for st in b.stages] == [st["views"] for st in a.stages]
        assert b.stages[0]["scan"]["kept"] == a.stages[0]["scan"]["kept"]
        assert b.converged == a.converged  # (best_start may differ: two starts tie)
        assert len(b.stages[-1]["final_loss"]) == (2 if branch else 1)


def test_photos_of_different_sizes_are_not_stacked(photos):
    s, f, t, _ = photos[0]
    s2, f2, t2, _ = photo(2.0, 4e4, 4, npix=24)
    fns = [make_residual_fn(*p, {"pixels": 1.0}) for p in ((s, f, t), (s2, f2, t2))]
    with pytest.raises(ConfigError, match="differs in structure"):
        stack_modules(fns)
    with pytest.raises(ConfigError, match="one space, forward template"):
        fit_many([s], [f, f], [t, t], starts=[starts_of(s)] * 2)


# --------------------------------------------------------------------------------------
# the table, the figures and the report folders


def result(sigma, truth, converged=True, chi2=1.02, stderr=0.01):
    return FitResult(
        paths=[SIGMA, "obs.flux"],
        values={SIGMA: sigma, "obs.flux": 5e4},
        stderr={SIGMA: stderr, "obs.flux": math.nan},
        covariance=np.eye(2),
        nuisance=["obs.flux"],
        truth={SIGMA: truth, "obs.flux": 5.1e4},
        loss=100.0,
        reduced_chi2=chi2,
        converged=converged,
        message="converged after 9 steps" if converged else "hit max_steps=5",
        n_steps=9,
        timing_s={"compile": 1.5, "solve": 0.25, "total": 2.0},
    )


def write_folder(folder, res, wall_s=3.0):
    folder.mkdir(parents=True)
    data = res.to_dict() | {"fit": {"wall_s": wall_s}}
    (folder / "params.json").write_text(json.dumps(data))


def test_table_lists_every_photo_with_values_errors_truth_and_failures(tmp_path):
    write_folder(tmp_path / "a", result(2.02, 2.01))  # inside 2 se, not on its edge
    write_folder(tmp_path / "b", result(2.9, 3.0, converged=False, chi2=40.0))
    tasks = [Task(n, tmp_path / n, None) for n in ("a", "b", "c")]
    outcomes = [Outcome("a", "ok"), Outcome("b", "not converged", "hit max_steps=5"),
                Outcome("c", "failed", "target photo c.exr is not a valid EXR")]  # fmt: skip
    rows = collect_rows(tasks, outcomes, {"a": "a.exr", "b": "b.exr", "c": "c.exr"})
    assert [r.status for r in rows] == ["ok", "not converged", "failed"]
    assert rows[0].wall_s == 3.0 and rows[2].result is None

    lines = to_csv(rows).splitlines()
    header = lines[0].split(",")
    assert header[:4] == ["photo", "name", "status", "converged"]
    assert f"{SIGMA} se" in header and f"{SIGMA} truth" in header and header[-1] == "reason"
    first = dict(zip(header, lines[1].split(","), strict=True))
    assert float(first[SIGMA]) == 2.02 and float(first[f"{SIGMA} se"]) == 0.01
    assert float(first[f"{SIGMA} truth"]) == 2.01 and float(first["wall_s"]) == 3.0
    assert first["obs.flux se"] == ""  # NaN is an empty cell
    assert lines[3].startswith("c.exr,c,failed,") and "not a valid EXR" in lines[3]

    md = to_markdown(rows, title="demo", figures=["histograms.png"])
    assert "3 photos: 1 converged, 0 converged to a poor fit, 1 not converged, 1 failed." in md
    assert "| [a](a/report.md) | ok | 2.02 ± 0.01 |" in md
    assert "- **c** (failed): target photo c.exr is not a valid EXR" in md
    assert "![histograms](histograms.png)" in md
    rec = {r["path"]: r for r in recovery(rows)}[SIGMA]
    assert rec["n"] == 2 and math.isclose(rec["max_abs_error"], 0.1)
    assert math.isclose(rec["max_rel_error"], 0.1 / 3.0) and rec["within_2se"] == 1


def test_population_figures_are_written(tmp_path):
    for i, (v, t) in enumerate([(2.0, 2.05), (2.5, 2.45), (3.1, 3.0)]):
        write_folder(tmp_path / f"p{i}", result(v, t))
    tasks = [Task(f"p{i}", tmp_path / f"p{i}", None) for i in range(3)]
    files = population_figures(tmp_path, collect_rows(tasks, [], {}))
    assert files == ["histograms.png", "fitted_vs_true.png"]
    assert all((tmp_path / f).stat().st_size > 1000 for f in files)


def test_short_names_are_unique_tails():
    paths = ["model.aperture.upper_lashes.count", "model.aperture.lower_lashes.count", "obs.flux"]
    assert short_names(paths) == {
        paths[0]: "upper_lashes.count", paths[1]: "lower_lashes.count", "obs.flux": "flux"
    }


def test_finished_needs_a_complete_fit_result_and_stale_temporaries_go(tmp_path):
    write_folder(tmp_path / "done", result(2.0, 2.0))
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "params.json").write_text('{"format": "invglare.fit", "param')
    assert finished(tmp_path / "done").values[SIGMA] == 2.0
    assert finished(tmp_path / "broken") is None and finished(tmp_path / "missing") is None
    stale = tmp_path / ".done.k2j3h4.tmp"
    stale.mkdir()
    (tmp_path / ".other.abc.tmp").mkdir()
    recover_unfinished([tmp_path / "done"])
    assert not stale.exists() and (tmp_path / ".other.abc.tmp").exists()
    assert finished(tmp_path / "done").values[SIGMA] == 2.0


# --------------------------------------------------------------------------------------
# the cluster's address


@pytest.mark.parametrize("address", ["localhost", "tcp://:8786", "http://host", "tcp://a b:1"])
def test_a_malformed_scheduler_address_is_refused(address):
    with pytest.raises(ConfigError, match="not a scheduler address"):
        check_address(address)


def test_an_unreachable_scheduler_is_a_clear_error_within_seconds():
    """Nothing listens on the port: the error names the address and how to start a
    scheduler, after the 2 s timeout asked for (the bound only guards against a hang)."""
    t0 = time.perf_counter()
    match = r"cannot reach a Dask scheduler at tcp://127\.0\.0\.1:9 .*dask scheduler"
    with pytest.raises(ConfigError, match=match):
        with dask_client("tcp://127.0.0.1:9", connect_timeout_s=2.0):
            pass
    assert time.perf_counter() - t0 < 30.0


_PIN_PROBE = """
import os, threading
from invglare.fit.batch import pin_to_core
stop = threading.Event()
before = threading.Thread(target=stop.wait); before.start()
core = pin_to_core(1)
after = threading.Thread(target=lambda: print(sorted(os.sched_getaffinity(0)))); after.start()
after.join(); stop.set(); before.join()
tids = [int(t) for t in os.listdir('/proc/self/task')]
print(core, sorted({c for t in tids for c in os.sched_getaffinity(t)}))
"""


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="core pinning is Linux-only")
def test_pin_to_core_pins_every_thread_and_the_ones_started_later():
    """In a fresh process (pinning this one would slow the rest of the suite): a thread
    running before the call, the caller and a thread started after all end on the second
    core this process may use (the first, cyclically, on a one-core machine)."""
    cores = sorted(os.sched_getaffinity(0))
    want = cores[1 % len(cores)]
    out = subprocess.run([sys.executable, "-c", _PIN_PROBE], capture_output=True, text=True,
                         check=True).stdout.split("\n")  # fmt: skip
    assert out[0] == f"[{want}]", out
    assert out[1] == f"{want} [{want}]", out


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="core pinning is Linux-only")
def test_local_cluster_workers_each_run_on_a_core_of_their_own():
    """dask_client's LocalCluster of 2 workers: each worker process is held to one core,
    worker i on the i-th core this process may use (cyclically), before any task runs."""
    cores = sorted(os.sched_getaffinity(0))
    with dask_client(None, 2, cache_dir=None) as client:
        held = client.run(lambda dask_worker: (dask_worker.name, sorted(os.sched_getaffinity(0))))
    assert sorted(held.values()) == [(i, [cores[i % len(cores)]]) for i in range(2)], held


def test_the_committed_population_batch_recovers_every_eye():
    """reports/eye_population/batch (``invglare fit-batch fits/eye_population.toml``, whose
    first stage frees the centre and branches the lash count into five starts): every eye
    converged, its pupil within 2 % and its lash count within 1 of the truth, reduced χ²
    about 1."""
    root = Path(__file__).resolve().parents[2]
    (stage,) = load_toml(root / "fits" / "eye_population.toml")["stage"]
    assert stage["branch"] == {"model.aperture.upper_lashes.count": [-2, -1, 0, 1, 2]}
    assert "fixed" not in stage
    folder = root / "reports" / "eye_population" / "batch"
    with open(folder / "batch.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 16
    pupil, count = "model.aperture.pupil.diameter_mm", "model.aperture.upper_lashes.count"
    for row in rows:
        assert row["status"] == "ok", (row["name"], row["reason"])
        assert abs(float(row[count]) - float(row[f"{count} truth"])) < 1.0, row["name"]
        assert abs(float(row[pupil]) / float(row[f"{pupil} truth"]) - 1.0) < 0.02, row["name"]
        assert abs(float(row["reduced_chi2"]) - 1.0) < 0.1, row["name"]
