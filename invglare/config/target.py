"""The ``[target]`` table of a fit config: the photo, its clip level and its ground truth.

Its keys (``file``, ``pixel_scale_deg``, ``saturation``, ``channel``, ``linear``,
``truth``) are in the schema of :mod:`invglare.config.fit`.

:func:`read_target_section` checks the table, :func:`load_target` reads and checks the
photo, :func:`read_truth` reads a synth truth file (``invglare synth`` writes one beside
every synthetic photo).

**Example:**

```python
target = read_target_section(config, Path("fits"))
photo, scale = load_target(target.path, saturation=target.saturation)
```
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np
from jaxtyping import Float

from invglare.config.section import Section
from invglare.errors import ConfigError, InputDataError
from invglare.files.photo import read_photo


@dataclasses.dataclass(frozen=True)
class TargetSection:
    """The checked ``[target]`` table: the photo's file, how to read it, its truth file.

    `path` and `truth_path` are resolved against the config's folder; `truth_path` (and
    `truth_file`, as written) is None when the table names no truth file (the default
    one beside the photo may still exist, see :func:`invglare.config.synth.truth_path_for`).
    """

    path: Path
    pixel_scale_deg: float | None
    saturation: float | None
    channel: str | None
    linear: bool
    truth_path: Path | None
    truth_file: str | None = None


def resolve(base: Path, value: str) -> Path:
    """`value` (``~`` expanded) relative to the folder `base` unless absolute, normalised."""
    p = Path(value).expanduser()
    return Path(os.path.normpath(p if p.is_absolute() else base / p))


def read_target_section(config: dict[str, Any], base: Path) -> TargetSection:
    """Check the ``[target]`` table of a parsed fit config whose folder is `base`.

    **Raises:** :class:`~invglare.errors.ConfigError` naming the key for a missing
    ``file``, unknown keys, wrong types, or a saturation that is not a level > 0.
    """
    sec = Section(config.get("target", {}), "target")
    target_file = sec.get("file", str, required=True)
    scale = sec.get("pixel_scale_deg", float, None)
    saturation = sec.get("saturation", float, None)
    channel = sec.get("channel", str, None)
    linear = sec.get("linear", bool, False)
    truth_file = sec.get("truth", str, None)
    sec.finish()
    if saturation is not None and not (math.isfinite(saturation) and saturation > 0):
        raise ConfigError(f"target.saturation must be a level > 0 counts, got {saturation!r}")
    return TargetSection(
        path=resolve(base, target_file),
        pixel_scale_deg=scale,
        saturation=saturation,
        channel=channel,
        linear=linear,
        truth_path=resolve(base, truth_file) if truth_file else None,
        truth_file=truth_file or None,
    )


def load_target(
    path: Path,
    *,
    channel: str | None = None,
    linear: bool = False,
    saturation: float | None = None,
    square: bool = True,
) -> tuple[Float[np.ndarray, "h w"], float | None]:
    """Read a target photo as float64 counts; **returns** ``(image, pixelScaleDeg or None)``.

    Refuses (:class:`~invglare.errors.InputDataError`, with the reason) a missing or
    unreadable file, a display-encoded integer image (8-bit PNG/JPEG, integer TIFF:
    tone-mapped, not linear counts) unless `linear`, a float image that looks
    tone-mapped (every value a multiple of 1/255 in [0, 1]) unless `linear`, a
    multi-channel image without `channel`, a non-square image (when `square`: the PSF
    models' grids are square, the veiling model's screen is not), NaN/inf pixels, an
    image that is all zeros or constant, and one whose every pixel is at `saturation`.

    **Example:** ``load_target(Path("photo.exr"), saturation=60000.0)``.
    """
    from invglare.fit.observation import check_target

    data, pixel_scale_deg = read_photo(path, channel=channel, linear=linear, square=square)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            data = check_target(data, saturation=saturation).astype(np.float64)
        except InputDataError as err:
            raise InputDataError(f"target photo {path}: {err}") from None
    for w in caught:
        if "tone-mapped" in str(w.message) and not linear:
            raise InputDataError(
                f"target photo {path}: {w.message}; set target.linear = true if it is linear"
            )
    return data, pixel_scale_deg


def read_truth(path: Path) -> tuple[dict[str, Any], dict[str, float]]:
    """The model config and observation fields of a synth truth file (``*.truth.json``).

    **Raises:** :class:`~invglare.errors.InputDataError` if the file cannot be read or
    lacks either.
    """
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        return data["model"], data["observation"]
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise InputDataError(
            f"ground truth {path} is not a readable synth truth file: {err}"
        ) from None
