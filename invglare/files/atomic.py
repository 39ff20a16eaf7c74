"""Atomic writes: a result is either completely there or not there at all.

**Files.** Every file invglare produces (EXR, PNG, JSON, reports) is first written to a
temporary file in the *same directory* as the target and then moved over it
with `os.replace`, which is atomic on POSIX and Windows when source and target
are on the same filesystem. A crash, a full disk or an exception in the writer
therefore never leaves a half-written file, and an existing file is only
replaced once its successor is complete. A temporary name holds its writer's pid, so
the next write of the same file removes what a killed writer left.

**Folders** (reports) are replaced as a whole by :func:`atomic_directory`, under the
folder's lock (:func:`folder_lock`: one run per folder; a second one is refused naming
the holder's pid). Replacing takes several renames; a journal written before the first
one makes them one transaction: a run killed between them is completed by the next run
that takes the lock (:func:`recover_folder`), so the new report is installed and the
entries it keeps (a sampled ``posterior/``) are never stranded in a hidden folder.
Temporary folders of killed runs that had not committed are removed, saying so.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import logging
import os
import re
import shutil
import tempfile
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from invglare.errors import FolderBusyError

__all__ = [
    "atomic_directory",
    "atomic_path",
    "atomic_write",
    "dumps_json",
    "folder_lock",
    "recover_folder",
    "write_json_atomic",
    "write_text_atomic",
]

log = logging.getLogger("invglare")

#: Test hook (:func:`pause_point`): a step of a folder swap (``"kept"``, ``"aside"``,
#: ``"installed"``) or of a chain step (``"chain-step"``), optionally ``@k``, at which the
#: process announces itself on stderr and sleeps, so a test can kill it there (or, with
#: SIGUSR1, let it go on).
PAUSE_ENV = "INVGLARE_TEST_PAUSE_AT"
#: Seconds a run waits for a folder another run holds before refusing (default 0).
LOCK_WAIT_ENV = "INVGLARE_LOCK_WAIT_S"


_PASSED: dict[str, int] = {}


def pause_point(name: str) -> None:
    """A test hook: pause here if ``INVGLARE_TEST_PAUSE_AT`` is `name` (or ``name@k``: the
    k-th time this point is passed), announcing it on stderr, so a test can kill the
    process at exactly this point. Does nothing otherwise."""
    wanted = os.environ.get(PAUSE_ENV)
    if not wanted or not wanted.startswith(name):
        return
    _PASSED[name] = _PASSED.get(name, 0) + 1
    at, _, nth = wanted.partition("@")
    if at == name and _PASSED[name] == int(nth or 1):
        import signal
        import sys
        import threading

        main = threading.current_thread() is threading.main_thread()
        if main:  # SIGUSR1 lets the run go on (a test that needs it held, not killed)
            signal.signal(signal.SIGUSR1, _resume)
        print(f"invglare: test pause at {wanted} (pid {os.getpid()})", file=sys.stderr, flush=True)
        try:
            with contextlib.suppress(_Resumed):
                time.sleep(3600)
        finally:
            if main:
                signal.signal(signal.SIGUSR1, signal.SIG_DFL)


class _Resumed(Exception):
    """Raised by SIGUSR1's handler to end a test pause (a handler that returns would not)."""


def _resume(signum: int, frame: object) -> None:
    raise _Resumed


def _temp_path_for(path: Path) -> Path:
    # Hidden, unique, with the writer's pid, and ending in the target's own suffix: writers
    # such as imageio choose the format from the extension of the path they are given.
    return path.parent / f".{path.name}.{os.getpid()}-{uuid.uuid4().hex[:12]}.tmp{path.suffix}"


def pid_alive(pid: int) -> bool:
    """Whether a process `pid` exists (on this machine)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _remove_stale_temps(path: Path) -> None:
    """Remove the temporary files of earlier writes of `path` whose writer is dead."""
    pattern = re.compile(rf"^\.{re.escape(path.name)}\.(\d+)-[0-9a-f]{{12}}\.tmp")
    try:
        entries = list(os.scandir(path.parent))
    except OSError:
        return
    for entry in entries:
        m = pattern.match(entry.name)
        if m and entry.is_file(follow_symlinks=False) and not pid_alive(int(m.group(1))):
            with contextlib.suppress(OSError):
                os.unlink(entry.path)
                log.warning("removed %s, left by a killed write of %s", entry.path, path.name)


def _fsync_file(path: Path) -> None:
    with open(path, "rb") as f:
        os.fsync(f.fileno())


def _fsync_dir(directory: Path) -> None:
    # Makes the rename itself durable; not possible on every OS/filesystem,
    # and the file is already complete without it, so failures are ignored.
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path to write to; move it onto `path` on success.

    The temporary file lives in `path`'s directory (created if needed) so the
    final `os.replace` is atomic. If the body raises, the temporary file is
    removed and an existing file at `path` is left untouched.

    **Arguments:**

    - `path`: the final destination.

    **Yields:** the temporary `Path`; the body must create the file there.

    ```python
    with atomic_path("out/psf.exr") as tmp:
        write_something(tmp)
    ```
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_temps(target)
    tmp = _temp_path_for(target)
    try:
        yield tmp
        if not tmp.is_file():
            raise FileNotFoundError(f"the writer did not create the temporary file {tmp}")
        _fsync_file(tmp)
        os.replace(tmp, target)
    except BaseException:
        # Also on KeyboardInterrupt: a stray temp file is litter in a results folder.
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(target.parent)


def atomic_write(path: str | os.PathLike[str], writer: Callable[[Path], None]) -> Path:
    """Write a file atomically by calling `writer(temporary_path)`.

    **Arguments:**

    - `path`: the final destination; parent directories are created.
    - `writer`: writes the complete file to the path it is given.

    **Returns:** `path` as a `Path`.

    If `writer` raises, the exception propagates, no temporary file is left
    behind and a pre-existing file at `path` is unchanged.
    """
    target = Path(path)
    with atomic_path(target) as tmp:
        writer(tmp)
    return target


def write_text_atomic(path: str | os.PathLike[str], text: str, *, encoding: str = "utf-8") -> Path:
    """Atomically write `text` to `path` (parents created). **Returns:** the path."""

    def _write(tmp: Path) -> None:
        # "x": never write through a file that someone else created meanwhile.
        with open(tmp, "x", encoding=encoding, newline="") as f:
            f.write(text)

    return atomic_write(path, _write)


def _json_default(obj: Any) -> Any:
    # Values that commonly end up in configs and results but that `json` refuses.
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if hasattr(obj, "__array__") and hasattr(obj, "shape"):  # jax arrays, without importing jax
        return np.asarray(obj).tolist()
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if isinstance(obj, _dt.date | _dt.time):  # TOML dates and times
        return obj.isoformat()
    if isinstance(obj, set | frozenset):
        return sorted(obj)
    raise TypeError(f"object of type {type(obj).__name__} is not JSON serialisable: {obj!r}")


def dumps_json(obj: Any, *, indent: int | None = 2) -> str:
    """Serialise `obj` to JSON, accepting numpy/JAX arrays and scalars, paths and dates.

    Raises `TypeError` naming the first value that cannot be serialised.
    """
    return json.dumps(obj, indent=indent, default=_json_default, ensure_ascii=False)


def write_json_atomic(path: str | os.PathLike[str], obj: Any, *, indent: int | None = 2) -> Path:
    """Atomically write `obj` as UTF-8 JSON (see `dumps_json`), ending in a newline.

    **Returns:** the path.
    """
    # Serialise first: a value that cannot be encoded must fail before any file work.
    text = dumps_json(obj, indent=indent) + "\n"
    return write_text_atomic(path, text)


# ----------------------------------------------------------------------------- folders

#: Folders this process holds the lock of: resolved path -> (fd, depth of nesting).
_HELD: dict[str, list[int]] = {}


def _lock_file(folder: Path) -> Path:
    return folder.parent / f".{folder.name}.lock"


def _journal_file(folder: Path) -> Path:
    return folder.parent / f".{folder.name}.swap.json"


def _holder(lock: Path) -> str:
    try:
        info = json.loads(lock.read_text(encoding="utf-8"))
        return f"pid {info['pid']}, {info['command']}, since {info['since']}"
    except (OSError, ValueError, KeyError, TypeError):
        return "pid unknown"


@contextlib.contextmanager
def folder_lock(path: str | os.PathLike[str], *, option: str = "the folder") -> Iterator[Path]:
    """Hold the lock of the output folder `path` for the body: one run per folder.

    The lock is an ``flock`` on the hidden sibling ``.NAME.lock`` (the kernel releases it
    when its holder dies, even by ``kill -9``), which records the holder's pid and
    command. A second run waits ``INVGLARE_LOCK_WAIT_S`` seconds (default 0) and then
    raises :class:`~invglare.errors.FolderBusyError` naming the holder and `option`.
    Taking the lock first completes or removes what a killed run left
    (:func:`recover_folder`). Nested use in one process is allowed.

    **Yields:** `path` as a `Path`.
    """
    import fcntl
    import sys

    target = Path(path)
    key = os.path.realpath(target)
    if key in _HELD:
        _HELD[key][1] += 1
        try:
            yield target
        finally:
            _HELD[key][1] -= 1
        return
    target.parent.mkdir(parents=True, exist_ok=True)
    lock = _lock_file(target)
    wait = float(os.environ.get(LOCK_WAIT_ENV, "0") or 0)
    deadline = time.monotonic() + wait
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            if time.monotonic() < deadline:
                time.sleep(0.2)
                continue
            raise FolderBusyError(
                f"{option} {str(target)!r} is in use by another invglare run ({_holder(lock)}); "
                f"wait until it ends, or choose another {option}"
            ) from None
        try:
            same = os.fstat(fd).st_ino == os.stat(lock).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)  # the holder removed that file as it let go: lock the new one
    info = {
        "pid": os.getpid(),
        "command": "invglare " + " ".join(sys.argv[1:3]) if sys.argv else "invglare",
        "since": time.strftime("%Y-%m-%d %H:%M:%S"),
    }
    os.ftruncate(fd, 0)
    os.write(fd, json.dumps(info).encode())
    _HELD[key] = [fd, 1]
    try:
        recover_folder(target)
        yield target
    finally:
        del _HELD[key]
        with contextlib.suppress(OSError):
            os.unlink(lock)
        os.close(fd)


def _leftovers(target: Path) -> tuple[list[Path], list[Path]]:
    """The hidden temporary (``.tmp``) and set-aside (``.old``) folders of `target`."""
    pattern = re.compile(rf"^\.{re.escape(target.name)}\.[^./]+\.(tmp|old)$")
    tmps, olds = [], []
    try:
        entries = list(os.scandir(target.parent))
    except OSError:
        return [], []
    for entry in entries:
        m = pattern.match(entry.name)
        if m and entry.is_dir(follow_symlinks=False):
            (tmps if m.group(1) == "tmp" else olds).append(Path(entry.path))
    return tmps, olds


def _finish_swap(target: Path, tmp: Path, old: Path, keep: Sequence[str]) -> None:
    """Complete (or redo) the swap of `tmp` into `target`; every step may be repeated."""
    if tmp.is_dir():
        if target.is_dir():
            for name in keep:
                if os.path.lexists(target / name) and not os.path.lexists(tmp / name):
                    os.replace(target / name, tmp / name)
                    pause_point("kept")
            os.replace(target, old)
            pause_point("aside")
        os.replace(tmp, target)
        pause_point("installed")
    elif not target.exists() and old.is_dir():
        os.replace(old, target)
    for name in keep:  # from a swap of an earlier version, which moved them last
        if os.path.lexists(old / name) and not os.path.lexists(target / name):
            os.replace(old / name, target / name)
    shutil.rmtree(old, ignore_errors=True)
    _fsync_dir(target.parent)


def recover_folder(path: str | os.PathLike[str]) -> list[str]:
    """Complete or undo what a killed run left beside the folder `path`; return what was done.

    Call it holding the folder's lock (:func:`folder_lock` does). A journal
    (``.NAME.swap.json``) means a complete new folder was being installed: the swap is
    finished. Without one, a temporary ``.NAME.*.tmp`` folder is an unfinished result and
    is removed; a set-aside ``.NAME.*.old`` folder gives back the entries the current
    folder lacks (the whole folder if there is none) and is removed. Each action is logged
    as a warning.
    """
    target = Path(path)
    done: list[str] = []
    journal = _journal_file(target)
    if journal.is_file():
        try:
            j = json.loads(journal.read_text(encoding="utf-8"))
            tmp, old = target.parent / j["tmp"], target.parent / j["old"]
            keep = list(j.get("keep", []))
        except (OSError, ValueError, KeyError, TypeError):
            journal.unlink()  # not readable: written partly, so nothing was moved yet
            done.append(f"removed the unreadable journal {journal.name}")
        else:
            _finish_swap(target, tmp, old, keep)
            journal.unlink()
            done.append(f"completed the replacement of {target} that a killed run had begun")
    tmps, olds = _leftovers(target)
    for old in olds:
        if not target.exists():
            os.replace(old, target)
            done.append(f"restored {target} from {old.name}, set aside by a killed run")
            continue
        for entry in sorted(os.listdir(old)):
            if not os.path.lexists(target / entry):
                os.replace(old / entry, target / entry)
                done.append(f"moved {entry} back into {target} from {old.name}")
        shutil.rmtree(old, ignore_errors=True)
        done.append(f"removed {old.name}, set aside by a killed run")
    for tmp in tmps:
        shutil.rmtree(tmp, ignore_errors=True)
        done.append(f"removed the unfinished {tmp.name} of a killed run")
    for message in done:
        log.warning("%s", message)
    return done


@contextlib.contextmanager
def atomic_directory(path: str | os.PathLike[str], keep: Sequence[str] = ()) -> Iterator[Path]:
    """Yield a temporary folder to fill; it replaces `path` as a whole on success.

    The temporary folder is a hidden sibling of `path` (same filesystem, so the
    renames are atomic), filled under the folder's lock (:func:`folder_lock`). On any
    exception, ``KeyboardInterrupt`` included, it is removed and an existing `path` is
    left as it was. Entries of the old `path` named in `keep` (and not written anew)
    move into the new one: a refit keeps the posterior chain of ``invglare sample``,
    which may have taken hours. The renames are journalled: a run killed between them
    is completed by the next (:func:`recover_folder`).
    """
    target = Path(path)
    with folder_lock(target):
        tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent))
        umask = os.umask(0)
        os.umask(umask)
        tmp.chmod(0o777 & ~umask)  # mkdtemp makes it private; a report folder is an ordinary one
        try:
            yield tmp
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        old = target.parent / f".{target.name}.{uuid.uuid4().hex[:12]}.old"
        journal = _journal_file(target)
        # Once the journal is there the new folder counts as installed: a kill from here
        # on is completed by the next run, never undone.
        write_json_atomic(journal, {"tmp": tmp.name, "old": old.name, "keep": list(keep)})
        _finish_swap(target, tmp, old, keep)
        journal.unlink()
