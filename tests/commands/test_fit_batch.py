"""`invglare fit-batch` on a real Dask LocalCluster of 2 worker processes.

Three small disk photos (a population drawn by `invglare synth`: pupils, fluxes, centres
and noise of their own) are fitted by one config; the batch must equal the serial
`invglare fit` of each photo, report a corrupt photo and finish the others, survive a
worker killed mid-task (its nanny restarts it, Dask reruns the task), and resume after
Ctrl-C without refitting finished photos. Bad input fails before any work, in seconds.
"""

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import disk_population
from typer.testing import CliRunner

from invglare.cli import app
from invglare.commands.fit import run_fit
from invglare.commands.fit_batch import run_fit_batch
from invglare.fit import FitResult
from invglare.fit.batch import worker_env

runner = CliRunner()
ROOT = Path(__file__).resolve().parents[2]
DIAMETER = "model.aperture.shapes[0].diameter_mm"
#: Photos in the population: three keep both workers of a 2-worker cluster busy (one fits
#: two) and leave photos to fit after the first when a batch is interrupted; a fourth
#: only added a fit (and its serial twin) per test.
N = 3

def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def crowd(tmp_path_factory):
    """The folder with model.toml, fit.toml and crowd/disk_0[0-2].exr (+ truths)."""
    return disk_population(tmp_path_factory.mktemp("crowd"), size=N)


@pytest.fixture(scope="module")
def worker_cache(tmp_path_factory):
    """JAX's persistent compilation cache of the batch workers (--cache-dir), shared by
    this module's batches, as a user's runs share ~/.cache/invglare/jax: the first batch's
    workers compile the fit, the later ones load it (measured: the corrupt-photo and
    killed-worker tests went from about 250 and 170 s of CPU to 125 and 80 s).
    Under CI's xdist workers, conftest's cache folder, which both share. The workers'
    XLA flags (one thread) give their programs keys of their own: the serial fits of this
    process still compile theirs."""
    shared = os.environ.get("JAX_COMPILATION_CACHE_DIR")
    return Path(shared) if shared else tmp_path_factory.mktemp("jax")


@pytest.fixture
def inside(crowd, monkeypatch):
    monkeypatch.chdir(crowd)
    return crowd


def params(folder: Path) -> dict:
    return json.loads((folder / "params.json").read_text())


# The Ctrl-C test comes first: its one worker compiles the fit into the workers' cache,
# from which the other batches' workers load it (one compile, not two in parallel) when
# they run after it (xdist may hand the tests to two pytest workers that run them side by
# side; they share the cache folder, so the later one loads whatever is there).


@pytest.mark.slow
def test_a_batch_interrupted_by_ctrl_c_resumes_without_refitting(inside, tmp_path, worker_cache):
    """Ctrl-C (SIGINT) once the first photo's report is written: exit 130, that report
    complete, no half-written one; the rerun skips it (its file untouched) and fits the rest."""
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-m", "invglare.cli", "fit-batch", "fit.toml", "crowd/*.exr",
           "--workers", "1", "--out-dir", str(out), "--cache-dir", str(worker_cache),
           "--no-progress"]  # fmt: skip
    # A run started in the background by a shell (`pytest ... &`) inherits SIGINT ignored,
    # which Python keeps: the child gets back the default a terminal's Ctrl-C meets.
    def default_sigint():
        signal.signal(signal.SIGINT, signal.SIG_DFL)

    proc = subprocess.Popen(
        cmd, cwd=inside, env=env, stderr=subprocess.PIPE, text=True, preexec_fn=default_sigint
    )
    first = out / "batch" / "disk_00" / "params.json"
    deadline = time.time() + 900
    while not first.exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.2)
    assert first.exists(), "the first photo never finished"
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "interrupted" in err
    folders = [p for p in (out / "batch").iterdir() if p.is_dir() and p.name[0] != "."]
    done = [p for p in folders if (p / "params.json").is_file()]
    assert done == folders and 1 <= len(done) < N  # no visible folder is half-written
    stamps = {p.name: (p / "params.json").stat().st_mtime_ns for p in done}

    summary = run_fit_batch(inside / "fit.toml", ["crowd/*.exr"], out_dir=out, workers=2,
                            progress=False, cache_dir=worker_cache)  # fmt: skip
    assert summary.skipped == len(done) and summary.fitted == N - len(done)
    assert [r.status for r in summary.rows] == ["ok"] * N
    for name, stamp in stamps.items():
        assert (out / "batch" / name / "params.json").stat().st_mtime_ns == stamp
    assert not [p for p in (out / "batch").iterdir() if re.match(r"^\..*\.(tmp|old)$", p.name)]
    # Nothing left to do: the table is kept as it is.
    md = (out / "batch" / "batch.md").stat().st_mtime_ns
    again = run_fit_batch(inside / "fit.toml", ["crowd/*.exr"], out_dir=out, progress=False)
    assert again.fitted == 0 and again.skipped == N
    assert (out / "batch" / "batch.md").stat().st_mtime_ns == md
    assert FitResult.from_json(out / "batch" / f"disk_{N - 1:02d}" / "params.json").converged


@pytest.mark.slow
def test_batch_equals_serial_fits_and_a_corrupt_photo_is_reported(inside, tmp_path, worker_cache):
    """Three photos and a corrupt one on 2 workers: exit status 1 naming the corrupt photo;
    the three match `invglare fit` of each photo alone to 1e-8 relative; the table holds
    every parameter with its error and the failure's reason."""
    (inside / "broken").mkdir(exist_ok=True)
    (inside / "broken" / "disk_99.exr").write_bytes(b"not an EXR at all")
    out = tmp_path / "out"
    res = invoke("fit-batch", "fit.toml", "crowd/*.exr", "broken/disk_99.exr", "--workers", 2,
                 "--out-dir", out, "--cache-dir", worker_cache, "--no-progress")  # fmt: skip
    assert res.exit_code == 1, res.output
    assert f"1 of {N + 1} photo(s) failed or did not converge: disk_99" in res.output
    batch = out / "batch"
    rows = (batch / "batch.csv").read_text().splitlines()
    assert len(rows) == N + 2
    assert rows[N + 1].startswith("broken/disk_99.exr,disk_99,failed,")
    assert "disk_99.exr" in rows[N + 1]
    for i in range(N):
        name = f"disk_{i:02d}"
        batched = params(batch / name)
        assert batched["converged"], batched["message"]
        assert (batch / name / "report.md").is_file() and (batch / name / "images.png").is_file()
        # The serial fit of the same photo, with the same config.
        config = (inside / "fit.toml").read_text().replace("disk_00", name)
        (inside / f"fit_{name}.toml").write_text(config)
        serial = params(run_fit(inside / f"fit_{name}.toml", out_dir=tmp_path / name,
                                progress=False))  # fmt: skip
        for path, entry in serial["parameters"].items():
            got = batched["parameters"][path]
            np.testing.assert_allclose(got["value"], entry["value"], rtol=1e-8, err_msg=path)
            np.testing.assert_allclose(got["stderr"], entry["stderr"], rtol=1e-6, err_msg=path)
            assert got["truth"] == entry["truth"]
        truth = json.loads((inside / "crowd" / f"{name}.truth.json").read_text())
        assert batched["parameters"][DIAMETER]["truth"] == truth["set"][DIAMETER]
    md = (batch / "batch.md").read_text()
    assert (
        f"{N + 1} photos: {N} converged, 0 converged to a poor fit, 0 not converged, 1 failed."
        in md
    )
    assert "- **disk_99** (failed): " in md
    assert (batch / "histograms.png").is_file() and (batch / "fitted_vs_true.png").is_file()


@pytest.mark.slow
def test_a_worker_killed_mid_task_is_replaced_and_every_photo_finishes(
    inside, tmp_path, worker_cache
):
    """A cluster of 2 worker processes (started here, used through --scheduler); once a
    worker is fitting, its process is killed (SIGKILL). Its nanny starts a new one, Dask
    reruns the task, and every photo ends with a report."""
    import dask
    from distributed import Client, LocalCluster

    # env: the XLA flags of invglare's own clusters, whose programs the cache holds.
    with dask.config.set({"distributed.worker.multiprocessing-method": "spawn"}):
        cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                               dashboard_address=":0", env=worker_env())  # fmt: skip
    killed = []
    try:
        watcher = Client(cluster)
        pids = watcher.run(os.getpid)

        def kill_a_busy_worker():
            deadline = time.time() + 600
            while time.time() < deadline and not killed:
                if any(watcher.processing().values()):
                    # Well inside the task: it is loading the photo, tracing (the compiled
                    # programs come from the cache), solving or writing the report.
                    time.sleep(2.0)
                    busy = [w for w, keys in watcher.processing().items() if keys]
                    if busy:  # a worker with a task now, not one that has just finished
                        os.kill(pids[busy[0]], signal.SIGKILL)
                        killed.append(pids[busy[0]])
                time.sleep(0.2)

        thread = threading.Thread(target=kill_a_busy_worker, daemon=True)
        thread.start()
        summary = run_fit_batch(inside / "fit.toml", ["crowd/*.exr"], out_dir=tmp_path / "out",
                                scheduler=cluster.scheduler_address, progress=False,
                                cache_dir=worker_cache)  # fmt: skip
        thread.join(timeout=5)
        assert killed, "no worker was busy"
        assert [r.status for r in summary.rows] == ["ok"] * N, [r.reason for r in summary.rows]
        assert len(watcher.scheduler_info()["workers"]) == 2  # the nanny replaced it
        assert killed[0] not in watcher.run(os.getpid).values()
        watcher.close()
    finally:
        cluster.close()


# --------------------------------------------------------------------------------------
# bad input: one clear line, exit status 2, before any work


@pytest.mark.parametrize(
    "args, message",
    [
        (["crowd/*.png"], r"the glob 'crowd/\*\.png' matches no photo"),
        (["table.csv"], r"unknown column\(s\) 'exposure'; valid columns: photo, name"),
        (["crowd/*.exr", "--vmap", "0"], "--vmap must be an integer >= 1"),
        (["crowd/*.exr", "--scheduler", "localhost"], "not a scheduler address"),
        (["crowd/*.exr", "--scheduler", "tcp://127.0.0.1:1", "--workers", "2"], "--workers starts"),
    ],
)
def test_bad_input_is_one_clear_error(inside, args, message):
    (inside / "table.csv").write_text("photo,exposure\ncrowd/disk_00.exr,1.0\n")
    res = invoke("fit-batch", "fit.toml", *args)
    assert res.exit_code == 2, res.output
    assert re.search(message, res.output), res.output


def test_an_unreachable_scheduler_fails_within_seconds(inside):
    """Nothing listens at the address: a clear error after the connect timeout (10 s),
    before the config is even loaded (the bound only guards against a hang)."""
    t0 = time.perf_counter()
    res = invoke("fit-batch", "fit.toml", "crowd/*.exr", "--scheduler", "tcp://127.0.0.1:9")
    assert res.exit_code == 2, res.output
    assert "cannot reach a Dask scheduler at tcp://127.0.0.1:9" in res.output
    assert "dask scheduler" in res.output and "dask worker" in res.output
    assert time.perf_counter() - t0 < 60.0


def test_a_reference_fit_config_is_refused(inside):
    res = invoke("fit-batch", ROOT / "fits" / "cie_A50_p1.toml", "crowd/*.exr")
    assert res.exit_code == 2 and "fits a reference glare function" in res.output
