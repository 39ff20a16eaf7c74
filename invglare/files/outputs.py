"""Output paths checked before any work: the one place every command asks "can I write there?".

A command that computes for an hour and then finds it cannot write its result has wasted
the hour; one that writes OpenEXR bytes under ``out.txt`` has misled its user. Every
command therefore hands each output path, with the option that named it, to
:func:`output_file` or :func:`output_folder` first. They refuse, in one line naming the
option:

- a file name whose extension is not one the command writes (listing the valid ones;
  formats are chosen by extension);
- a file path that is an existing folder, a folder path that is an existing file;
- a path under an existing file (``blocker/x.exr``);
- a folder that cannot be written (permissions, a read-only or immutable filesystem):
  this is probed by creating and removing a hidden file in the nearest existing folder,
  which is what decides (root ignores permission bits, ``os.access`` does not see
  read-only mounts or immutable folders).

Missing folders are not created here (a refused run leaves nothing behind): the writers
create them (:mod:`invglare.files.atomic`).

**Example:**

```python
out = output_file("psf.exr", "--out", (".exr",))
report = output_folder("reports/eye", "--out-dir", replaced=True)
```
"""

from __future__ import annotations

import errno
import os
import tempfile
from collections.abc import Sequence
from pathlib import Path

from invglare.errors import ConfigError

__all__ = ["REPORTS_DIR", "RUNS_DIR", "check_disk", "output_file", "output_folder"]

#: Where the commands write by default (fits, posteriors, batches, the gallery, the
#: benchmark, the regression): git-ignored, so that a user's run never rewrites a committed
#: report. Name a folder under :data:`REPORTS_DIR` with ``--out-dir`` to refresh one.
RUNS_DIR = Path("runs")

#: The committed reports of the bundled fits, benchmark, gallery and regression.
REPORTS_DIR = Path("reports")


def _named(option: str, path: Path) -> str:
    return f"{option} {str(path)!r}"


def _listed(suffixes: Sequence[str]) -> str:
    """``".exr"``, ``".exr or .png"``, ``".exr, .png or .gif"``."""
    return " or ".join([", ".join(suffixes[:-1]), suffixes[-1]] if len(suffixes) > 1 else suffixes)


def _nearest_existing(path: Path) -> Path:
    p = path
    while not os.path.lexists(p) and p != p.parent:
        p = p.parent
    return p


def _probe_writable(folder: Path, option: str, path: Path) -> None:
    """Create and remove a hidden file in `folder` (what decides whether it can be written)."""
    try:
        fd, probe = tempfile.mkstemp(prefix=".invglare-probe-", dir=folder)
    except OSError as err:
        why = err.strerror or type(err).__name__
        if err.errno == errno.EROFS:
            why = "read-only filesystem"
        raise ConfigError(
            f"{_named(option, path)}: the folder {str(folder)!r} is not writable ({why}); "
            "choose another place"
        ) from None
    os.close(fd)
    os.unlink(probe)


def _check_parent(path: Path, option: str) -> None:
    """`path`'s folder exists and is writable, or can be made (its nearest existing
    ancestor is a writable folder)."""
    base = _nearest_existing(path.parent)
    if not base.is_dir():
        raise ConfigError(
            f"{_named(option, path)}: {str(base)!r} is not a folder (it is a file), so "
            "nothing can be written under it"
        )
    _probe_writable(base, option, path)


def output_file(path: str | os.PathLike[str], option: str, suffixes: Sequence[str]) -> Path:
    """Check an output file path; return it as a `Path`.

    **Arguments:**

    - `path`: where the command will write.
    - `option`: the option (or key) the user gave it with, e.g. ``"--out"``, for messages.
    - `suffixes`: the extensions the command writes (lower case, with the dot); the
      format is chosen by the extension, so any other one is refused with this list.

    **Raises:** :class:`~invglare.errors.ConfigError` (see the module docstring).
    """
    target = Path(path)
    if target.is_dir():
        raise ConfigError(
            f"{_named(option, target)} is a folder; give a file name ending in "
            f"{_listed(suffixes)}"
        )
    suffix = target.suffix.lower()
    if suffix not in suffixes:
        shown = f"extension {suffix!r}" if suffix else "no extension"
        raise ConfigError(
            f"{_named(option, target)} has {shown}; the format is chosen by the extension: "
            f"{_listed(suffixes)}"
        )
    _check_parent(target, option)
    return target


def output_folder(
    path: str | os.PathLike[str], option: str, *, replaced: bool = False
) -> Path:
    """Check an output folder; return it as a `Path`.

    `replaced`: the folder is replaced as a whole (a report folder, see
    :func:`invglare.files.atomic.atomic_directory`): its parent must be writable, and so
    must the folder itself if it exists (its old entries are moved and removed).

    **Raises:** :class:`~invglare.errors.ConfigError` (see the module docstring).
    """
    target = Path(path)
    if os.path.lexists(target) and not target.is_dir():
        raise ConfigError(
            f"{_named(option, target)} is not a folder (it is a file); give a folder"
        )
    if target.is_dir():
        _probe_writable(target, option, target)
        if replaced:
            _check_parent(target, option)
    else:
        _check_parent(target, option)
    return target


def check_disk(nbytes: float, path: str | os.PathLike[str], what: str) -> None:
    """Refuse to write `nbytes` under `path` when its filesystem has less room.

    **Raises:** :class:`~invglare.errors.MemoryLimitError` with the estimate and the room.
    """
    import shutil

    from invglare._core.memory import shown_bytes
    from invglare.errors import MemoryLimitError

    base = _nearest_existing(Path(path))
    try:
        free = shutil.disk_usage(base if base.is_dir() else base.parent).free
    except OSError:
        return
    if nbytes > free:
        raise MemoryLimitError(
            f"{what} needs about {shown_bytes(nbytes)} of disk; the limit is the "
            f"{shown_bytes(free)} free under {str(base)!r}"
        )
