"""The photos of a batch fit: globs, folders and photo tables, read and checked up front.

``invglare fit-batch fits/NAME.toml PHOTOS...`` takes one fit config and any mix of

- a **glob** (``"data/*.exr"``; quote it so that the shell leaves it to invglare),
- a **folder** (every photo in it: ``.exr``, ``.tif``, ``.tiff``),
- a **photo file**,
- a **photo table** (``.csv``): one row per photo, a ``photo`` column (paths relative to
  the table) and optional per-photo overrides of the config's ``[target]`` table:

```text
photo,name,pixel_scale_deg,saturation,channel,linear,truth
night/p001.exr,subject_1,0.003,60000,,,
night/p002.tif,subject_2,0.0031,,Y,false,p002_truth.json
```

An empty cell keeps the config's value. :func:`read_photos` checks everything that can
be checked before a worker starts (a glob that matches nothing, a missing file, unknown
columns, values of the wrong type, two photos with one name); whether a photo can be
*fitted* (readable, linear, not all clipped) is each photo's own outcome, recorded in the
batch table. :func:`photo_config` puts one photo into the fit config's tables.

**Example:**

```python
jobs = read_photos(["data_synthetic/eye_population/*.exr"])
config = photo_config(load_toml("fits/eye_population.toml"), jobs[0])
```
"""

from __future__ import annotations

import copy
import csv
import dataclasses
import glob
import math
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from invglare.config.target import resolve
from invglare.errors import ConfigError

#: File suffixes taken from a folder (linear photos; display-encoded files need a table
#: row with ``linear = true``).
PHOTO_SUFFIXES = (".exr", ".tif", ".tiff")
#: Suffixes read as photo tables.
TABLE_SUFFIXES = (".csv",)
#: Columns of a photo table: the photo, its name in the reports, ``[target]`` overrides.
TABLE_COLUMNS = ("photo", "name", "pixel_scale_deg", "saturation", "channel", "linear", "truth")
_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")
_GLOB = re.compile(r"[*?\[]")


@dataclasses.dataclass(frozen=True)
class PhotoJob:
    """One photo of a batch.

    - `name`: its report folder's name (the file's stem unless a table names it).
    - `path`: the photo, absolute.
    - `target`: overrides of the fit config's ``[target]`` table (``pixel_scale_deg``,
      ``saturation``, ``channel``, ``linear``; ``truth`` as an absolute path).
    """

    name: str
    path: Path
    target: Mapping[str, Any] = dataclasses.field(default_factory=dict)


def read_photos(sources: Sequence[str | Path], cwd: Path | None = None) -> list[PhotoJob]:
    """The photos `sources` name (globs, folders, files, photo tables), in order.

    **Arguments:**

    - `sources`: as on the command line (module docstring); relative to `cwd`.
    - `cwd`: the folder relative paths start from (default: the current one).

    **Returns:** one :class:`PhotoJob` per photo, each photo once.

    **Raises:** :class:`~invglare.errors.ConfigError` naming the source for no sources, a
    glob that matches nothing, a folder without photos, a file that does not exist, a
    table with unknown or missing columns or a bad cell, or two photos with one name.
    """
    base = Path.cwd() if cwd is None else Path(cwd)
    if not sources:
        raise ConfigError("no photos given: name photo files, folders, globs or a .csv table")
    jobs: list[PhotoJob] = []
    for source in sources:
        text = str(source)
        path = resolve(base, text)
        if _GLOB.search(text) and not path.exists():
            pattern = text if Path(text).is_absolute() else str(base / text)
            matches = sorted(Path(m) for m in glob.glob(pattern, recursive=True))
            photos = [m for m in matches if m.is_file() and m.suffix.lower() in PHOTO_SUFFIXES]
            if not photos:
                raise ConfigError(
                    f"the glob {text!r} matches no photo ({', '.join(PHOTO_SUFFIXES)} files)"
                    + (f"; it matched {len(matches)} other paths" if matches else "")
                )
            jobs += [PhotoJob(p.stem, p) for p in photos]
        elif path.is_dir():
            photos = sorted(p for p in path.iterdir() if p.suffix.lower() in PHOTO_SUFFIXES)
            if not photos:
                suffixes = ", ".join(PHOTO_SUFFIXES)
                raise ConfigError(f"the folder {text!r} holds no photo ({suffixes})")
            jobs += [PhotoJob(p.stem, p) for p in photos]
        elif not path.is_file():
            raise ConfigError(f"the photo {text!r} does not exist ({path})")
        elif path.suffix.lower() in TABLE_SUFFIXES:
            jobs += read_photo_table(path)
        else:
            jobs.append(PhotoJob(path.stem, path))
    return _unique(jobs)


def read_photo_table(path: Path) -> list[PhotoJob]:
    """The rows of a photo table (``.csv``, module docstring) as :class:`PhotoJob` s.

    **Raises:** :class:`~invglare.errors.ConfigError` naming the table, the row and the
    column for unknown or missing columns, an empty table, a photo that does not exist
    and cells that are not of their column's type.
    """
    try:
        with open(path, newline="", encoding="utf-8") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise ConfigError(f"cannot read the photo table {path}: {err}") from None
    rows = [r for r in rows if any(cell.strip() for cell in r)]
    if not rows:
        raise ConfigError(
            f"the photo table {path} is empty; it needs a header row and a 'photo' column"
        )
    header = [cell.strip() for cell in rows[0]]
    unknown = [c for c in header if c not in TABLE_COLUMNS]
    if unknown:
        raise ConfigError(
            f"the photo table {path} has unknown column(s) {', '.join(map(repr, unknown))}; "
            f"valid columns: {', '.join(TABLE_COLUMNS)}"
        )
    if "photo" not in header:
        raise ConfigError(
            f"the photo table {path} has no 'photo' column (header: {', '.join(header)})"
        )
    if len(set(header)) != len(header):
        raise ConfigError(f"the photo table {path} names a column twice: {', '.join(header)}")
    if len(rows) < 2:
        raise ConfigError(f"the photo table {path} lists no photo (only its header)")
    jobs = []
    for number, row in enumerate(rows[1:], start=2):
        where = f"{path}, line {number}"
        if len(row) != len(header):
            raise ConfigError(f"{where}: {len(row)} cells for {len(header)} columns")
        cells = {c: v.strip() for c, v in zip(header, row, strict=True) if v.strip()}
        if "photo" not in cells:
            raise ConfigError(f"{where}: the 'photo' cell is empty")
        photo = resolve(path.parent, cells.pop("photo"))
        if not photo.is_file():
            raise ConfigError(f"{where}: the photo {photo} does not exist")
        name = cells.pop("name", photo.stem)
        target = {col: _cell(col, value, where, path.parent) for col, value in cells.items()}
        jobs.append(PhotoJob(name, photo, target))
    return jobs


def _cell(column: str, value: str, where: str, base: Path) -> Any:
    """A photo table's cell as its ``[target]`` key's type."""
    if column in ("pixel_scale_deg", "saturation"):
        try:
            number = float(value)
        except ValueError:
            number = math.nan
        if not (math.isfinite(number) and number > 0):
            raise ConfigError(f"{where}: {column} = {value!r} must be a number > 0")
        return number
    if column == "linear":
        flags = {"true": True, "1": True, "yes": True, "false": False, "0": False, "no": False}
        if value.lower() not in flags:
            raise ConfigError(f"{where}: linear = {value!r} must be true or false")
        return flags[value.lower()]
    if column == "truth":
        truth = resolve(base, value)
        if not truth.is_file():
            raise ConfigError(f"{where}: the truth file {truth} does not exist")
        return str(truth)
    return value  # channel


def _unique(jobs: list[PhotoJob]) -> list[PhotoJob]:
    """Each photo once (a file named twice, e.g. by a glob and by name, is fitted once);
    every name valid and used once."""
    seen: dict[Path, PhotoJob] = {}
    for job in jobs:
        seen.setdefault(job.path.resolve(), job)
    names: dict[str, Path] = {}
    for job in seen.values():
        if not _NAME.match(job.name):
            raise ConfigError(
                f"photo {job.path}: its name {job.name!r} must be a plain name (letters, digits, "
                "_ - .); give it one in a photo table's 'name' column"
            )
        if job.name in names:
            raise ConfigError(
                f"two photos would share the report folder {job.name!r}: {names[job.name]} and "
                f"{job.path}; name them in a photo table ('name' column)"
            )
        names[job.name] = job.path
    return list(seen.values())


def photo_config(config: Mapping[str, Any], job: PhotoJob) -> dict[str, Any]:
    """The fit config's tables with `job`'s photo as the target (and its overrides).

    The config's own ``target.truth`` belongs to its own photo and is dropped: each photo's
    truth is its table's ``truth`` or, as for ``invglare fit``, ``NAME.truth.json``
    beside it. ``fit.name`` becomes the photo's name (its report's title); ``fit.out_dir``
    is dropped (the batch decides where each report goes).
    """
    out = copy.deepcopy(dict(config))
    if not isinstance(out.get("target", {}), dict):
        raise ConfigError(f"[target] must be a table, got {out['target']!r}")
    target = dict(out.get("target", {}))
    target.pop("truth", None)
    target["file"] = str(job.path)
    target.update(job.target)
    out["target"] = target
    fit = dict(out.get("fit", {})) if isinstance(out.get("fit"), dict) else {}
    fit.pop("out_dir", None)
    fit["name"] = job.name
    out["fit"] = fit
    return out
