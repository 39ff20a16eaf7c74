"""Bad input through every subcommand and config kind: one clean line, never a traceback.

Each case of :data:`bad_inputs.CASES` must end with a non-zero exit, exactly one line on
stderr (``invglare: error: ...``) matching the case's pattern (it names the option, key or
file at fault), no traceback, in under 30 s and under 2 GB of memory. Most cases run in
this process through typer's CliRunner (the command's own code, its own error handling);
the size cases run in a subprocess under an address-space limit, so that a missing check
fails the test with a MemoryError instead of swapping the machine, and their peak memory
is the child's own.

Read-only folders: CI runs as root, which ignores permission bits. A root run makes the
folder immutable (``chattr +i``: not even root can create a file in it, checked by the
fixture); any other user gets ``chmod 555``.
"""

from __future__ import annotations

import os
import re
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from bad_inputs import CASES, SUBCOMMANDS, WORLD_FILES, Bad, edit_toml
from typer.testing import CliRunner

from invglare.cli import app

ROOT = Path(__file__).resolve().parents[2]
GB = 1024**3
#: Address-space limit of the subprocess cases: JAX maps ~1.5 GB at import.
CHILD_ADDRESS_LIMIT = 5 * GB
#: The memory limit the commands see: lower than the machine's, so that "too big" is
#: decided by the estimate and stays the same on any machine the suite runs on.
MEMORY_LIMIT = "3G"
runner = CliRunner()


def _rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def _maxrss_bytes(who=resource.RUSAGE_SELF) -> int:
    return resource.getrusage(who).ru_maxrss * 1024


#: A folder in which not even root can create anything (sysfs), for file systems or
#: containers where ``chattr +i`` is refused (overlayfs, no CAP_LINUX_IMMUTABLE).
_SYSFS_FOLDER = Path("/sys/kernel")


def _make_unwritable(folder: Path) -> None:
    """`folder` becomes a folder nobody can write into (made, or linked to one)."""
    folder.mkdir()
    if os.geteuid() != 0:
        folder.chmod(0o555)
    elif subprocess.run(["chattr", "+i", str(folder)], capture_output=True).returncode != 0:
        folder.rmdir()
        folder.symlink_to(_SYSFS_FOLDER, target_is_directory=True)
    with pytest.raises(OSError):  # the premise of the read-only cases
        (folder / "probe").write_text("x")


def _make_writable(folder: Path) -> None:
    if folder.is_symlink():
        folder.unlink()
        return
    if os.geteuid() == 0:
        subprocess.run(["chattr", "-i", str(folder)], check=False, capture_output=True)
    folder.chmod(0o755)


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """Copies of the bundled configs, tiny configs, odd files, scenes and a fit photo."""
    from invglare.files.exr import write_exr

    d = tmp_path_factory.mktemp("bad_input_world")
    for sub in ("examples", "fits", "data_synthetic"):
        shutil.copytree(ROOT / sub, d / sub)
    for name, content in WORLD_FILES.items():
        path = d / name
        if isinstance(content, bytes):
            path.write_bytes(content)
        else:
            path.write_text(content, encoding="utf-8")
    for case in CASES:
        for name, (_, src, section, key, value) in case.files:
            (d / name).write_text(edit_toml((d / src).read_text(), section, key, value))
    with open(d / "huge.toml", "wb") as f:  # sparse: 64 MiB on paper, nothing on disk
        f.truncate(64 * 2**20)
    rng = np.random.default_rng(0)
    scene = rng.uniform(0.0, 1.0, (32, 32, 3)).astype(np.float32)
    scene[16, 16] = 5000.0
    write_exr(d / "scene.exr", scene, pixel_scale_deg=0.01)
    write_exr(d / "dark_scene.exr", np.zeros((32, 32, 3), np.float32), pixel_scale_deg=0.01)
    neg = scene.copy()
    neg[3, 4, 1] = -2.0
    write_exr(d / "neg_scene.exr", neg, pixel_scale_deg=0.01, attrs=None)
    nan_row = np.where(np.arange(32)[:, None] == 5, np.nan, scene[..., 0])
    _write_raw_exr(d / "nan_scene.exr", nan_row)
    _write_raw_exr(d / "noscale_scene.exr", scene[..., 0])
    y, x = np.mgrid[:32, :32] - 16
    photo = 20.0 + 1e5 * np.exp(-(x**2 + y**2) / 8.0) / (8 * np.pi)
    write_exr(d / "photo.exr", photo.astype(np.float32), pixel_scale_deg=0.004)
    (d / "chaindir" / "posterior" / "chain.h5").mkdir(parents=True)
    (d / "fitted").mkdir()
    (d / "out").mkdir()
    (d / "tests").mkdir()
    (d / "tests" / "golden").symlink_to(ROOT / "tests" / "golden")  # regress reads them
    ro = d / "readonly"
    _make_unwritable(ro)
    yield d
    _make_writable(ro)


def _write_raw_exr(path: Path, plane: np.ndarray) -> None:
    """An EXR written without invglare's checks (NaN pixels, no pixelScaleDeg)."""
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    channels = {"Y": np.ascontiguousarray(plane, dtype=np.float32)}
    with OpenEXR.File(header, channels) as f:
        f.write(str(path))


def _check_one_line(case: Bad, code: int, stderr: str, stdout: str, seconds: float) -> None:
    assert "Traceback" not in stderr + stdout, f"{case.id}: traceback\n{stderr}"
    assert code != 0, f"{case.id}: accepted silently (exit 0)\n{stdout}\n{stderr}"
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1, f"{case.id}: expected one line on stderr, got\n{stderr}"
    line = lines[0]
    assert line.startswith(("invglare: error: ", "Usage:", "Error:")) or "Invalid value" in line, (
        f"{case.id}: {line}"
    )
    assert re.search(case.match, line), f"{case.id}: {line!r} does not match {case.match!r}"
    assert seconds < 30, f"{case.id}: took {seconds:.1f} s"


def test_the_table_covers_every_subcommand_and_config_kind():
    """>= 150 cases; every subcommand, every bundled config kind, the subprocess classes."""
    import typer.main

    commands = set(typer.main.get_command(app).commands)
    assert set(SUBCOMMANDS) <= commands
    used = {case.argv[0] for case in CASES}
    assert commands - {"fit-batch"} <= used, f"subcommands without a bad input: {commands - used}"
    assert len(CASES) >= 150 and len({c.id for c in CASES}) == len(CASES)
    sources = {src for c in CASES for _, (_, src, *_rest) in c.files}
    assert any(s.startswith("fits/") for s in sources)
    assert any(s.startswith("data_synthetic/") for s in sources)
    kinds = {re.search(r'kind = "(\w+)"', (ROOT / s).read_text()).group(1)
             for s in sources if s.startswith("examples/")}  # fmt: skip
    assert kinds >= {"aperture", "eye", "camera", "veiling", "temporal", "holographic"}


@pytest.mark.parametrize("case", [c for c in CASES if not c.sub], ids=lambda c: c.id)
def test_bad_input_is_one_clean_line(case: Bad, world: Path, monkeypatch):
    monkeypatch.chdir(world)
    monkeypatch.setenv("INVGLARE_MEMORY_LIMIT", MEMORY_LIMIT)
    before, high = _rss_bytes(), _maxrss_bytes()
    t0 = time.perf_counter()
    result = runner.invoke(app, ["-q", *case.args(world)])
    seconds = time.perf_counter() - t0
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        import traceback

        tb = "".join(traceback.format_exception(result.exception))
        pytest.fail(f"{case.id}: traceback\n{tb}")
    _check_one_line(case, result.exit_code, result.stderr, result.stdout, seconds)
    # The case's own peak: if it raised the process's high-water mark, that mark less what
    # the process held before (a mark set earlier, by another test of the worker, is not it).
    after = _maxrss_bytes()
    assert after == high or after - before < 2 * GB


#: Runs the oversized cases in one child under an address-space limit (one JAX import for
#: all): each case's outcome as a JSON line, and the child's peak memory after each.
CHILD = """
import json, os, resource, sys, time, traceback
limit = int(sys.argv[1])
resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
os.chdir(sys.argv[2])
from typer.testing import CliRunner
from invglare.cli import app
runner = CliRunner()
def peak_rss():
    # VmHWM is this program's own peak: ru_maxrss would keep the forking pytest worker's
    # (a worker several GB deep into the suite) across fork and exec.
    try:
        with open("/proc/self/status") as status:
            for row in status:
                if row.startswith("VmHWM:"):
                    return int(row.split()[1]) * 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
for line in sys.stdin:
    case = json.loads(line)
    t0 = time.perf_counter()
    r = runner.invoke(app, ["-q", *case["args"]])
    tb = None
    if r.exception is not None and not isinstance(r.exception, SystemExit):
        tb = "".join(traceback.format_exception(r.exception))
    print(json.dumps(dict(id=case["id"], code=r.exit_code, stderr=r.stderr, stdout=r.stdout,
                          traceback=tb, seconds=time.perf_counter() - t0,
                          maxrss=peak_rss())),
          flush=True)
"""


@pytest.fixture(scope="module")
def oversized(world):
    """The outcome of every oversized case, from one child process."""
    import json

    path = os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])
    env = dict(os.environ, JAX_PLATFORMS="cpu", INVGLARE_MEMORY_LIMIT=MEMORY_LIMIT, PYTHONPATH=path)
    cases = "".join(
        json.dumps({"id": c.id, "args": c.args(world)}) + "\n" for c in CASES if c.sub
    )
    done = subprocess.run(
        [sys.executable, "-c", CHILD, str(CHILD_ADDRESS_LIMIT), str(world)], input=cases,
        env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    results = {r["id"]: r for r in map(json.loads, done.stdout.splitlines())}
    assert len(results) == sum(c.sub for c in CASES), done.stderr[-3000:]
    return results


@pytest.mark.slow  # one child for all of them: a JAX import and ~20 refusals, ~1 min
@pytest.mark.parametrize("case", [c for c in CASES if c.sub], ids=lambda c: c.id)
def test_oversized_input_is_refused_before_allocating(case: Bad, oversized):
    """Under a 5 GB address-space limit: refused from the estimate, and the child's peak
    memory (every case so far) under 2 GB."""
    r = oversized[case.id]
    assert r["traceback"] is None, f"{case.id}: traceback\n{r['traceback']}"
    _check_one_line(case, r["code"], r["stderr"], r["stdout"], r["seconds"])
    assert r["maxrss"] < 2 * GB
