"""Every command and Python block of the README runs as written.

The README's fenced ``bash`` and ``python`` blocks are run section by section (a ``##``
heading; its blocks in order, in one scratch copy of the repository's data folders, so that
a block can read what an earlier one of its section wrote and nothing committed is
overwritten), with `invglare` on the PATH running this checkout's package. The long ones
run smaller, as the README says (its "Run the tests" paragraph): each change is listed in
:data:`SMALLER` with the reason, and must apply; a step that another test runs in full
through the same command is listed in :data:`RUN_IN_FULL` and not run twice. ``pip
install`` steps are left to the environment and the test command to CI, which runs it
verbatim (checked here against ``.ci/run``). A step whose comment documents a non-zero
exit status ("exit status 1") must end with it. The README's one example of an error
message is reproduced, and its ``toml`` blocks parse (the model configs among them build).
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"

#: Folders a README command reads (or writes, as the fit and sample reports), copied for
#: each section.
DATA = ("examples", "fits", "data_synthetic", "reports", "tests/golden")

#: (what the README says, what the test runs, why smaller). Every entry must apply.
SMALLER: tuple[tuple[str, str, str], ...] = (
    (
        '"data_synthetic/eye_population/*.exr" --workers 2',
        '"data_synthetic/eye_population/eye_00.exr" --workers 1',
        "1 of the 16 photos on one worker (each worker compiles the fit anew, and two "
        "compiled it side by side): the committed batch of all 16 is checked by "
        "tests/fit/test_batch.py and the batch machinery on a real 2-worker cluster by "
        "tests/commands/test_fit_batch.py",
    ),
    (
        "invglare fit fits/cie_A50_p1.toml",
        "invglare fit fits/cie_A50_p1.toml --max-steps 2 --no-progress",
        "the reference fit's own tests are in tests/cie_study/",
    ),
    ("--frames 120", "--frames 4", "an animation's frames all run the same compiled scan"),
    ("--frames 30", "--frames 4", "as above"),
    ("psf_sequence(30, 10.0)", "psf_sequence(4, 10.0)", "as above"),
    ("render_sequence(m, im, 30,", "render_sequence(m, im, 4,", "as above"),
    (
        "--iterations 64",
        "--iterations 4",
        "each random-phase draw is one more call of the same compiled chunk (one draw a call "
        "on a CPU); 64 draws cost 5 s of CPU more than 4 in the two holographic renders",
    ),
    ("--resume --steps 2000", "--resume --steps 1504", "4 steps more than the committed chain"),
    ("--restart", "--restart --steps 4 --walkers 16", "a new chain of 4 steps"),
)

#: Steps run by the environment, not by this test: installs, and the test command itself.
NOT_RUN = (re.compile(r"^pip install "), re.compile(r"^python -m pytest\b"))

#: (step, test, why): steps that another test runs in full through the same CLI command, so
#: that this one does not run them again (even shortened, each took minutes of compiling and
#: scatter draws). Every entry must name a step the README has and a test that runs it.
RUN_IN_FULL: tuple[tuple[str, str, str], ...] = (
    (
        "invglare fit fits/eye_daylight.toml",
        "tests/fit/test_fit_cli.py::test_bundled_fit_recovers_the_truth",
        "the README's main job, checked against the truth",
    ),
    (
        "invglare fit fits/eye_daylight_other_draws.toml",
        "tests/fit/test_other_draws.py::test_a_daylight_eye_the_model_did_not_draw",
        "checked against the truth and its flags",
    ),
)
IN_FULL_STEPS = frozenset(step for step, _test, _why in RUN_IN_FULL)


@dataclass(frozen=True)
class Block:
    section: str
    lang: str
    line: int
    text: str


def readme_blocks(text: str) -> list[Block]:
    """The fenced blocks of the README with the ``##`` section each stands in."""
    blocks, section = [], "top"
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        line = lines[i]
        if line.startswith("## "):
            section = line[3:].strip()
        fence = re.match(r"^```(\w*)\s*$", line)
        if fence:
            j = i + 1
            while not lines[j].startswith("```"):
                j += 1
            blocks.append(Block(section, fence.group(1), i + 1, "\n".join(lines[i + 1 : j])))
            i = j
        i += 1
    return blocks


BLOCKS = readme_blocks(README.read_text(encoding="utf-8"))
RUNNABLE = [b for b in BLOCKS if b.lang in ("bash", "python")]
SECTIONS = list(dict.fromkeys(b.section for b in RUNNABLE))


#: A step whose comment says "exit status N" is documented to end so, and must.
EXIT_STATUS = re.compile(r"#.*\bexit status (\d+)\b")


def shell_steps(block: Block) -> list[str]:
    """A bash block's commands (comments dropped), each `&&` chain split into its steps."""
    return [step for step, _status in shell_steps_with_status(block)]


def shell_steps_with_status(block: Block) -> list[tuple[str, int]]:
    """Each step of :func:`shell_steps` with the exit status its comment documents (0)."""
    steps = []
    for line in block.text.splitlines():
        command, _, comment = line.partition(" #")
        documented = EXIT_STATUS.search("#" + comment)
        status = int(documented.group(1)) if documented else 0
        steps += [(part.strip(), status) for part in command.split("&&") if command.strip()]
    return steps


def smaller(text: str) -> str:
    for said, run, _why in SMALLER:
        text = text.replace(said, run)
    return text


def test_every_smaller_size_applies():
    """Each entry of SMALLER changes a command the README has (none has rotted away)."""
    text = "\n".join(b.text for b in RUNNABLE)
    for said, _run, why in SMALLER:
        assert said in text, f"{said!r} ({why}) is no longer in the README"


def test_steps_run_in_full_elsewhere_are_run_there():
    """Each RUN_IN_FULL step is in the README, and the test named for it exists and invokes
    the same command on the same config."""
    steps = {step for b in RUNNABLE if b.lang == "bash" for step in shell_steps(b)}
    for step, node, _why in RUN_IN_FULL:
        assert step in steps, f"{step!r} is no longer a step of the README"
        path, name = node.split("::")
        source = (ROOT / path).read_text(encoding="utf-8")
        assert f"def {name}(" in source, f"{node} does not exist"
        body = source.split(f"def {name}(", 1)[1].split("\ndef ", 1)[0]
        command, config = step.split()[1:3]
        assert "invoke(" in body and f'"{command}"' in body, f"{node} does not invoke {command}"
        assert Path(config).stem in body or Path(config).stem in source, (node, config)


def test_the_readme_test_command_is_what_ci_runs():
    (test_block,) = [b for b in RUNNABLE if "python -m pytest" in b.text]
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert test_block.text.strip() in ci


def test_the_first_command_installs_no_torch():
    """The main job's install is the package's own dependencies, which do not name torch."""
    first = RUNNABLE[0]
    assert shell_steps(first)[0] == "pip install -e ."
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    assert not [d for d in deps if re.match(r"torch\b", d)]


@pytest.fixture
def scratch(tmp_path):
    """A copy of the data folders and an `invglare` on the PATH running this checkout."""
    work = tmp_path / "repo"
    for name in DATA:
        shutil.copytree(ROOT / name, work / name)
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    shim = bin_dir / "invglare"
    shim.write_text(f'#!/bin/sh\nexec {shlex.quote(sys.executable)} -m invglare.cli "$@"\n')
    shim.chmod(0o755)
    env = dict(os.environ)
    env["PATH"] = f"{bin_dir}{os.pathsep}{env['PATH']}"
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env["OMP_WAIT_POLICY"] = "PASSIVE"  # torch and JAX share the CPU (README, PyTorch)
    return work, env


def _run(args: list[str], work: Path, env: dict, what: str, status: int = 0) -> None:
    done = subprocess.run(args, cwd=work, env=env, capture_output=True, text=True, timeout=1200)
    assert done.returncode == status, (
        f"{what} exited {done.returncode}, the README says {status}:"
        f"\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    )


@pytest.mark.slow
@pytest.mark.parametrize("section", SECTIONS)
def test_readme_section_runs(section, scratch):
    work, env = scratch
    ran = elsewhere = 0
    for block in (b for b in RUNNABLE if b.section == section):
        where = f"README.md:{block.line} ({section})"
        if block.lang == "python":
            script = work / f"readme_{block.line}.py"
            script.write_text(smaller(block.text) + "\n")
            _run([sys.executable, str(script)], work, env, where)
            ran += 1
            continue
        for step, status in shell_steps_with_status(block):
            if any(p.match(step) for p in NOT_RUN):
                continue
            if step in IN_FULL_STEPS:
                elsewhere += 1
                continue
            args = ["bash", "-euo", "pipefail", "-c", smaller(step)]
            _run(args, work, env, f"{where}: {step}", status)
            ran += 1
    assert ran + elsewhere > 0


def test_the_error_example_is_what_the_command_prints(tmp_path):
    """The README's `invglare psf bad.toml` line, with circle.toml's disk key misspelt."""
    (example,) = [b for b in BLOCKS if b.lang == "" and b.text.startswith("$ invglare")]
    command, expected = example.text.splitlines()
    config = (ROOT / "examples" / "circle.toml").read_text()
    assert "diameter_mm = 4.0" in config
    (tmp_path / "bad.toml").write_text(config.replace("diameter_mm = 4.0", "diameter = 4.0", 1))
    done = subprocess.run(
        [sys.executable, "-m", "invglare.cli", *shlex.split(command)[2:]],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert done.returncode == 2
    assert done.stderr.strip().splitlines()[-1] == expected


@pytest.mark.parametrize("block", [b for b in BLOCKS if b.lang == "toml"], ids=lambda b: b.line)
def test_readme_toml_blocks_parse_and_model_configs_build(block):
    from invglare.config.model import build_model

    config = tomllib.loads(block.text)
    model = config.get("model", {})
    if "kind" in model and "config" not in model:
        build_model(config, base_dir=ROOT / "examples")
