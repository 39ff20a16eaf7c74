"""`kill -9` of a sampling process: the chain keeps the counters of an uninterrupted run.

A child samples the linear-Gaussian toy of `test_sample.py` and is killed with SIGKILL
inside a checkpoint (between writing a step and committing it, held there by the test
hook ``INVGLARE_TEST_PAUSE_AT=chain-step@k``) and at random moments; each time the chain
is resumed. The final chain, its acceptance counters and its random state must be those
of one uninterrupted run with the same seed, and the run history must name each killed
run and the step it reached.
"""

from __future__ import annotations

import itertools
import os
import random
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import x64
from test_sample import toy_analytic, toy_fit_result, toy_problem

from invglare.errors import InputDataError
from invglare.fit.sample import load_chain, sample

HERE = Path(__file__).resolve().parent
N_STEPS = 60
KW = dict(n_walkers=8, until_converged=False, batch_size=8, progress=False, seed=7)


def _child(path: Path, pause: str | None) -> subprocess.Popen:
    script = textwrap.dedent(
        f"""
        import sys
        sys.path[:0] = [{str(HERE)!r}, {str(HERE.parent)!r}]
        import jax
        jax.config.update("jax_enable_x64", True)
        from test_sample import toy_problem, toy_analytic, toy_fit_result
        from invglare.fit.sample import sample
        space, fwd, target = toy_problem()
        res = toy_fit_result(space, *toy_analytic(target))
        resume = {path.is_file()!r}
        sample(space, fwd, target, res, {str(path)!r}, max_steps=100000, resume=resume,
               **{KW!r})
        """
    )
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env.pop("INVGLARE_TEST_PAUSE_AT", None)
    if pause:
        env["INVGLARE_TEST_PAUSE_AT"] = pause
    return subprocess.Popen([sys.executable, "-c", script], env=env, stderr=subprocess.PIPE,
                            text=True)  # fmt: skip


def _stored(path: Path) -> int:
    try:
        return load_chain(path).n_steps
    except InputDataError:
        return 0


def _kill_when(proc: subprocess.Popen, ready) -> None:
    deadline = time.monotonic() + 300
    while not ready():
        assert proc.poll() is None, proc.stderr.read()
        assert time.monotonic() < deadline, "the child never got there"
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=60)


@pytest.mark.slow
def test_kills_during_checkpoints_and_at_random_leave_an_uninterrupted_chain(tmp_path):
    with x64():
        space, fwd, target = toy_problem()
        res = toy_fit_result(space, *toy_analytic(target))
        ref = sample(space, fwd, target, res, tmp_path / "ref.h5", max_steps=N_STEPS, **KW)

    path = tmp_path / "chain.h5"
    # 1. Inside the checkpoint of step 7: its rows are written, its counter not yet.
    proc = _child(path, "chain-step@7")
    _kill_when(proc, lambda: "test pause at" in proc.stderr.readline())
    first = load_chain(path)
    assert first.n_steps == 6
    # A reader sees the killed run's record closed at the counter, before any resume.
    (run,) = first.runs
    assert run["stopped"] == "killed" and run["end_step"] == 6 and run["n_steps"] == 6
    # 2. Twice more at a random moment of the sampling, each after a resume.
    rng = random.Random(1)
    for _ in range(2):
        start = _stored(path)
        proc = _child(path, None)
        goal = start + rng.randint(3, 12)
        _kill_when(proc, lambda goal=goal: _stored(path) >= goal)
        time.sleep(rng.uniform(0.0, 0.2))
    with x64():
        killed = load_chain(path)
        assert killed.n_steps < N_STEPS
        after = sample(space, fwd, target, res, path, max_steps=N_STEPS, resume=True, **KW)

    np.testing.assert_array_equal(after.latent, ref.latent)
    np.testing.assert_array_equal(after.log_prob, ref.log_prob)
    # The counters: acceptance per walker, not one count ahead on any.
    np.testing.assert_array_equal(after.acceptance * N_STEPS, ref.acceptance * N_STEPS)
    runs = after.runs
    assert [r["stopped"] for r in runs] == ["killed", "killed", "killed", "step limit"]
    assert runs[0]["start_step"] == 0 and runs[0]["end_step"] == 6
    for a, b in itertools.pairwise(runs):
        assert a["end_step"] == b["start_step"]
        assert a["n_steps"] == a["end_step"] - a["start_step"]
    assert runs[-1]["end_step"] == N_STEPS
