"""A fit's solve is loaded from JAX's persistent compilation cache by the next process.

The solve keeps its loss history inside the compiled program; only a live progress report
needs a host callback, and JAX never loads a program with one from its cache. Here two fresh
processes share one cache folder: the second loads the solve the first compiled, and its
recorded history equals the first's and the first's live progress reports.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

_SCRIPT = """
import json, math, sys
import jax, numpy as np
from helpers import GaussPSF
from invglare.fit import Forward, Observation, Parameter, ParameterSpace, fit

jax.config.update("jax_enable_x64", True)
truth = Observation(flux=5e4, background=10.0, read_noise=2.0)
target = np.asarray(truth.sample(jax.random.key(4), GaussPSF(2.4, 24)()))
template = Forward(GaussPSF(3.0, 24), Observation.from_target(target, read_noise=2.0))
space = ParameterSpace(
    [Parameter("model.sigma_px", 1.0, 5.0, init=3.0)],
    nuisance=[Parameter("obs.flux", 0.0, math.inf, init=float(template.obs.flux))],
)
out = {}
if sys.argv[1] == "live":
    seen = []
    res = fit(space, template, target, n_starts=2, progress=seen.append, diagnostics=False)
    out["live"] = [[p.loss for p in seen if p.start == i] for i in range(2)]
res = fit(space, template, target, n_starts=2, diagnostics=False)
out["history"] = res.loss_history[0]
out["value"] = res.values["model.sigma_px"]
print("RESULT " + json.dumps(out))
"""


def _run(mode: str, cache: Path) -> tuple[dict, str]:
    tests = Path(__file__).resolve().parents[1]
    env = os.environ | {
        "JAX_COMPILATION_CACHE_DIR": str(cache),
        "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0",
        "JAX_LOG_COMPILES": "1",  # logs every persistent-cache hit with the program's name
        "PYTHONPATH": os.pathsep.join([str(tests), os.environ.get("PYTHONPATH", "")]),
    }
    done = subprocess.run([sys.executable, "-c", _SCRIPT, mode], env=env, capture_output=True,
                          text=True, timeout=600)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    line = next(s for s in done.stdout.splitlines() if s.startswith("RESULT "))
    return json.loads(line[len("RESULT ") :]), done.stderr


@pytest.mark.slow
def test_the_next_process_loads_the_solve_from_the_persistent_cache(tmp_path):
    first, _ = _run("live", tmp_path / "cache")
    second, log = _run("quiet", tmp_path / "cache")
    assert "Persistent compilation cache hit for 'jit__batched'" in log
    assert second["history"] == first["history"] and second["value"] == first["value"]
    assert abs(first["value"] - 2.4) < 0.1
    for live, recorded in zip(first["live"], first["history"], strict=True):
        # The live reports are the accepted losses; the record ends with the final loss,
        # which repeats the last accepted one (dropped) unless the last step was accepted.
        assert len(recorded) >= 3 and len(live) in (len(recorded) - 1, len(recorded))
        assert live == pytest.approx(recorded[: len(live)], rel=1e-12)
