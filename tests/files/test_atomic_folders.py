"""Report folders under kills and concurrent runs: the lock, the journalled swap, recovery.

A child process replaces a report folder (`atomic_directory`, keeping ``posterior/``) and
is killed with SIGKILL at each step of the swap, held there by the test hook
``INVGLARE_TEST_PAUSE_AT``, or while it fills the new folder. Whatever the moment, the
final path holds a complete report (old or new), ``posterior/`` is never only in a hidden
folder once the next run has recovered, and the next run leaves no hidden leftovers.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from invglare.errors import FolderBusyError
from invglare.files.atomic import atomic_directory, folder_lock, recover_folder

ROOT = Path(__file__).resolve().parents[2]

#: A child that replaces `folder` by a complete new report, keeping posterior/.
CHILD = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    from invglare.files.atomic import atomic_directory
    folder, hold = Path(sys.argv[1]), sys.argv[2] == "hold"
    with atomic_directory(folder, keep=("posterior",)) as tmp:
        (tmp / "report.md").write_text("new")
        if hold:  # killed while filling the new report
            print("invglare: test pause at filling", file=sys.stderr, flush=True)
            time.sleep(3600)
        (tmp / "params.json").write_text('{"version": "new"}')
    """
)


def _old_report(folder: Path) -> None:
    (folder / "posterior").mkdir(parents=True)
    (folder / "posterior" / "chain.h5").write_text("hours of sampling")
    (folder / "report.md").write_text("old")
    (folder / "params.json").write_text('{"version": "old"}')


def _start(folder: Path, pause: str | None, hold: bool = False) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop("INVGLARE_TEST_PAUSE_AT", None)
    if pause:
        env["INVGLARE_TEST_PAUSE_AT"] = pause
    return subprocess.Popen(
        [sys.executable, "-c", CHILD, str(folder), "hold" if hold else "go"],
        env=env, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip


def _wait_for_pause(proc: subprocess.Popen) -> str:
    line = proc.stderr.readline()
    assert "test pause at" in line, line
    return line


def _kill(proc: subprocess.Popen) -> None:
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)


def _report_version(folder: Path) -> str:
    """'old' or 'new': the folder holds one complete report, never a mix or a part."""
    assert (folder / "report.md").is_file() and (folder / "params.json").is_file()
    version = json.loads((folder / "params.json").read_text())["version"]
    assert (folder / "report.md").read_text() == version
    return version


def _hidden(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.parent.iterdir() if p.name.startswith("."))


@pytest.mark.parametrize(
    ("pause", "hold", "after_recovery"),
    [
        (None, True, "old"),  # killed while filling: nothing committed
        ("kept", False, "new"),  # journal written, posterior moved into the new report
        ("aside", False, "new"),  # the old report set aside, the new not yet in place
        ("installed", False, "new"),  # the new report in place, the old not yet removed
    ],
)
def test_kill_during_a_report_swap_never_strands_the_posterior(
    tmp_path, caplog, pause, hold, after_recovery
):
    folder = tmp_path / "eye"
    _old_report(folder)
    proc = _start(folder, pause, hold)
    _wait_for_pause(proc)
    _kill(proc)
    # Right after the kill: the final path holds a complete report or none (mid-swap);
    # the posterior is somewhere, and the journal says where the swap stood.
    if folder.exists():
        _report_version(folder)
    with caplog.at_level("WARNING", logger="invglare"), folder_lock(folder):
        pass  # the next run takes the lock, which first recovers
    assert caplog.records, "a killed run's leftovers must be reported"
    assert _report_version(folder) == after_recovery
    assert (folder / "posterior" / "chain.h5").read_text() == "hours of sampling"
    assert _hidden(folder) == []


def test_next_run_recovers_and_then_replaces(tmp_path, caplog):
    """The killed swap is completed when the next run takes the lock, saying so."""
    folder = tmp_path / "eye"
    _old_report(folder)
    proc = _start(folder, "aside")
    _wait_for_pause(proc)
    _kill(proc)
    assert not folder.exists()  # the old report is aside, the new one not yet in place
    with caplog.at_level("WARNING", logger="invglare"):
        with atomic_directory(folder, keep=("posterior",)) as tmp:
            (tmp / "report.md").write_text("newer")
            (tmp / "params.json").write_text('{"version": "newer"}')
    assert "completed the replacement" in caplog.text
    assert _report_version(folder) == "newer"
    assert (folder / "posterior" / "chain.h5").is_file()
    assert _hidden(folder) == []


def test_leftovers_of_an_earlier_version_give_back_the_posterior(tmp_path, caplog):
    """The stranding the issue found: posterior/ left in a hidden .old folder, no journal."""
    folder = tmp_path / "eye"
    (folder).mkdir()
    (folder / "report.md").write_text("new")
    old = tmp_path / ".eye.0123456789ab.old"
    (old / "posterior").mkdir(parents=True)
    (old / "posterior" / "chain.h5").write_text("chain")
    (tmp_path / ".eye.abcdef.tmp").mkdir()
    with caplog.at_level("WARNING", logger="invglare"):
        recover_folder(folder)
    assert (folder / "posterior" / "chain.h5").read_text() == "chain"
    assert "moved posterior back" in caplog.text and "removed the unfinished" in caplog.text
    assert _hidden(folder) == []


def test_a_second_run_is_refused_naming_the_holder(tmp_path):
    folder = tmp_path / "eye"
    holder = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(f"""
            import sys, time
            from invglare.files.atomic import folder_lock
            with folder_lock({str(folder)!r}):
                print("locked", flush=True)
                time.sleep(3600)
            """)],
        env=dict(os.environ, PYTHONPATH=str(ROOT)), stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(FolderBusyError, match=rf"--out-dir .*pid {holder.pid}\b"):
            with folder_lock(folder, option="--out-dir"):
                pass
    finally:
        _kill(holder)
    # The kernel released the dead holder's lock: the next run gets it.
    with folder_lock(folder):
        assert (tmp_path / ".eye.lock").is_file()
    assert _hidden(folder) == []


def test_lock_is_reentrant_and_waits_when_asked(tmp_path, monkeypatch):
    folder = tmp_path / "eye"
    with folder_lock(folder), atomic_directory(folder) as tmp:  # fit holds it, then writes
        (tmp / "report.md").write_text("x")
    assert (folder / "report.md").read_text() == "x"
    monkeypatch.setenv("INVGLARE_LOCK_WAIT_S", "5")
    holder = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(f"""
            import time
            from invglare.files.atomic import folder_lock
            with folder_lock({str(folder)!r}):
                print("locked", flush=True)
                time.sleep(1.0)
            """)],
        env=dict(os.environ, PYTHONPATH=str(ROOT)), stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert holder.stdout.readline().strip() == "locked"
    t0 = time.monotonic()
    with folder_lock(folder):
        waited = time.monotonic() - t0
    holder.wait(timeout=30)
    assert 0.2 < waited < 5


def test_a_killed_file_write_is_cleaned_by_the_next_write(tmp_path, caplog):
    from invglare.files.atomic import write_text_atomic

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)  # fmt: skip
    stale = tmp_path / f".psf.exr.{int(dead.stdout)}-0123456789ab.tmp.exr"
    stale.write_text("half an EXR")
    with caplog.at_level("WARNING", logger="invglare"):
        write_text_atomic(tmp_path / "psf.exr", "whole")
    assert not stale.exists() and "left by a killed write" in caplog.text
    assert sorted(p.name for p in tmp_path.iterdir()) == ["psf.exr"]
