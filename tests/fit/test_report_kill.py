"""`invglare fit` and `invglare sample` killed with SIGKILL, and run side by side.

On a 32-px disk photo: fits are killed between the renames of the report folder's swap
(held there by ``INVGLARE_TEST_PAUSE_AT``) and at a random moment; after each kill the
report folder is complete or (mid-swap) absent, never partial, and what it keeps
(``posterior/``) is not lost; the next run recovers it. A sample is killed at a random
step and resumed. Two fits started into one folder end with one complete report and a
one-line refusal naming the other's pid.
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from invglare.errors import InputDataError

ROOT = Path(__file__).resolve().parents[2]

MODEL = """
[model]
kind = "aperture"
focal_length_mm = 17.0
aperture_npix = 32
window_mm = 5.4

[[model.shapes]]
kind = "disk"
diameter_mm = 3.5

[output]
npix = 32
pixel_scale_deg = 0.005

[spectrum]
wavelengths_nm = 550
"""

SPEC = """
[synth]
model = "model.toml"
seed = 2
out = "photo"
pixel_type = "float"

[set]
"model.aperture.shapes[0].diameter_mm" = 3.2

[observation]
flux = 1e6
background = 20.0
gain = 2.0
read_noise = 3.0
"""

FIT = """
[fit]
out_dir = "report"

[target]
file = "photo.exr"

[model]
config = "model.toml"

[observation]
gain = 2.0
read_noise = 3.0

[[free]]
path = "model.aperture.shapes[0].diameter_mm"
lower = 2.5
upper = 4.5
init = 3.4

[[free]]
path = "obs.flux"
lower = 0.0
upper = inf

[solver]
n_starts = 1
max_steps = 30
"""


def _env(pause: str | None = None) -> dict[str, str]:
    path = os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=path)
    env.pop("INVGLARE_TEST_PAUSE_AT", None)
    if pause:
        env["INVGLARE_TEST_PAUSE_AT"] = pause
    return env


def _invglare(folder: Path, *args: str, pause: str | None = None) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "invglare.cli", *args], cwd=folder, env=_env(pause),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip


def _run(folder: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "invglare.cli", *args], cwd=folder,
                          env=_env(), capture_output=True, text=True, timeout=600)  # fmt: skip


def _wait_for_pause(proc: subprocess.Popen) -> None:
    for line in proc.stderr:
        if "test pause at" in line:
            return
    pytest.fail(f"the run ended without pausing (exit {proc.wait()})")


def _kill_at_pause(proc: subprocess.Popen) -> None:
    _wait_for_pause(proc)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=60)


def _kill_after(proc: subprocess.Popen, seconds: float) -> None:
    time.sleep(seconds)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=60)


def _check_report(report: Path, *, absent_ok: bool = False) -> None:
    """Complete (params.json parses, report.md and figures there) or, mid-swap, absent."""
    if absent_ok and not report.exists():
        return
    assert json.loads((report / "params.json").read_text())["parameters"]
    assert (report / "report.md").read_text().strip()
    assert (report / "images.png").stat().st_size > 0


def _kept_somewhere(folder: Path) -> bool:
    """The posterior's notes are in the report or in a folder the journal will install."""
    return any(p.read_text() == "kept" for p in folder.rglob("notes.txt"))


@pytest.fixture(scope="module")
def problem(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("report_kill")
    (folder / "model.toml").write_text(MODEL)
    (folder / "spec.toml").write_text(SPEC)
    (folder / "fit.toml").write_text(FIT)
    done = _run(folder, "synth", "spec.toml")
    assert done.returncode == 0, done.stderr
    done = _run(folder, "fit", "fit.toml", "--no-progress")
    assert done.returncode == 0, done.stderr
    (folder / "report" / "posterior").mkdir()
    (folder / "report" / "posterior" / "notes.txt").write_text("kept")
    return folder


@pytest.mark.slow
def test_killed_fits_never_leave_a_partial_report_nor_strand_the_posterior(problem):
    report = problem / "report"
    rng = random.Random(3)
    for pause in ("kept", "aside", "installed", None):
        proc = _invglare(problem, "fit", "fit.toml", "--no-progress", pause=pause)
        if pause is None:
            _kill_after(proc, rng.uniform(1.0, 6.0))  # loading, compiling or solving
        else:
            _kill_at_pause(proc)
        _check_report(report, absent_ok=pause == "aside")
        assert _kept_somewhere(problem)
    done = _run(problem, "fit", "fit.toml", "--no-progress")
    assert done.returncode == 0, done.stderr
    _check_report(report)
    assert (report / "posterior" / "notes.txt").read_text() == "kept"
    assert sorted(p.name for p in problem.iterdir() if p.name.startswith(".")) == []


@pytest.mark.slow
def test_two_fits_into_one_folder_one_report_and_one_clear_refusal(problem):
    # The first is held inside its report folder's swap (it holds the folder's lock there)
    # while the second starts: on a loaded machine a first run left to go on had finished
    # before the second reached the lock, and the second fitted too.
    first = _invglare(problem, "fit", "fit.toml", "--no-progress", pause="kept")
    _wait_for_pause(first)
    second = _run(problem, "fit", "fit.toml", "--no-progress")
    first.send_signal(signal.SIGUSR1)
    _, err = first.communicate(timeout=600)
    assert first.returncode == 0, err
    assert second.returncode == 2, second.stderr
    (line,) = [ln for ln in second.stderr.splitlines() if ln.strip()]
    assert line.startswith("invglare: error: fit.out_dir 'report' is in use by another")
    assert f"pid {first.pid}," in line
    _check_report(problem / "report")
    assert (problem / "report" / "posterior" / "notes.txt").read_text() == "kept"


@pytest.mark.slow
def test_a_killed_sample_resumes_into_a_complete_posterior(problem):
    args = ["sample", "fit.toml", "--no-progress", "--walkers", "8", "--batch-size", "8",
            "--force"]  # fmt: skip
    from invglare.fit.sample.chain import stored_iteration

    chain = problem / "report" / "posterior" / "chain.h5"
    proc = _invglare(problem, *args, "--steps", "100000")
    deadline = time.monotonic() + 300
    goal = random.Random(5).randint(2, 30)
    def reached() -> bool:
        # HDF5 is not readable while the sampler writes a step: a torn read means "not yet".
        try:
            return chain.is_file() and stored_iteration(chain) >= goal
        except InputDataError:
            return False

    while not reached():
        assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=60)
    total = stored_iteration(chain) + 20
    done = _run(problem, *args, "--steps", str(total), "--resume")
    assert done.returncode == 0, done.stderr
    summary = json.loads((problem / "report" / "posterior" / "summary.json").read_text())
    assert summary["n_steps"] == total
    assert [r["stopped"] for r in summary["runs"]] == ["killed", "step limit"]
    assert summary["runs"][0]["end_step"] == summary["runs"][1]["start_step"] == total - 20
    assert (problem / "report" / "posterior" / "notes.txt").read_text() == "kept"
