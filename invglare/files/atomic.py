"""Atomic file writes: a result is either completely there or not there at all.

Every file invglare produces (EXR, PNG, JSON, reports) is first written to a
temporary file in the *same directory* as the target and then moved over it
with `os.replace`, which is atomic on POSIX and Windows when source and target
are on the same filesystem. A crash, a full disk or an exception in the writer
therefore never leaves a half-written file, and an existing file is only
replaced once its successor is complete.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import os
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "atomic_path",
    "atomic_write",
    "dumps_json",
    "write_json_atomic",
    "write_text_atomic",
]


def _temp_path_for(path: Path) -> Path:
    # Hidden, unique, and ending in the target's own suffix: writers such as
    # imageio choose the format from the extension of the path they are given.
    return path.parent / f".{path.name}.{uuid.uuid4().hex[:12]}.tmp{path.suffix}"


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
