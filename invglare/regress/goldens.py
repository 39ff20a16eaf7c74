"""The stored golden PSFs: where they live, what their header holds, and how they change.

The PSF of a case was computed once, in float32 on the CPU, and stored as an EXR file
``<golden_dir>/<case>.exr`` whose header holds the full model config
(``invglareConfig``), the pixel scale, the wavelengths and the case's name and light
angle.

**Updating.** :func:`update_goldens` rewrites the stored PSFs of the cases that
differ (or are missing) and appends to ``<golden_dir>/CHANGES.md`` the date, the reason
and the metrics of the stored PSFs *before* the update, so every change of the physics
is recorded with its size.

**Example:**

```python
results = run_suite(golden_dir="tests/golden")
update_goldens(results, "tests/golden", reason="new FFT normalisation")
```
"""

from __future__ import annotations

import datetime as dt
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from invglare.errors import ConfigError
from invglare.regress.cases import Case
from invglare.regress.compare import metric_cells

if TYPE_CHECKING:
    from invglare.regress.run import CaseResult

__all__ = ["CHANGES_FILE", "golden_path", "header_for", "update_goldens", "write_golden"]

#: Name of the change log kept next to the golden files.
CHANGES_FILE = "CHANGES.md"


def golden_path(golden_dir: str | os.PathLike[str], case: Case) -> Path:
    """Where the golden PSF of `case` lives: ``<golden_dir>/<name>.exr``."""
    return Path(golden_dir) / f"{case.name}.exr"


def header_for(case: Case, model: Any) -> tuple[dict[str, Any], dict[str, Any], list[float]]:
    """What a golden's header holds for `case`: ``(config, attrs, wavelengths_nm)``.

    The full model config (every default explicit, as the model's ``to_config()`` writes it),
    the case's own attributes, and the wavelengths the model computes.
    """
    config = model.to_config()
    attrs: dict[str, Any] = {
        "regressionCase": case.name,
        "regressionDescription": case.description,
        "propagationMethod": model.header()["propagationMethod"],
        "psfNormalisation": "fraction of the power through the aperture per pixel",
    }
    if case.light_angle_deg is not None:
        attrs["lightAngleDeg"] = [float(a) for a in case.light_angle_deg]
    lams = list(model.wavelengths_nm)
    return config, attrs, lams


def write_golden(path: str | os.PathLike[str], case: Case, psf: np.ndarray, model: Any) -> Path:
    """Store `psf` as the golden of `case` (float32 EXR, config and case in the header)."""
    from invglare.files.exr import write_exr

    config, attrs, lams = header_for(case, model)
    return write_exr(
        path,
        np.asarray(psf, dtype=np.float32),
        pixel_scale_deg=float(model.pixel_scale_deg),
        wavelengths_nm=lams,
        config=config,
        attrs=attrs,
    )


_CHANGES_HEADER = """# Golden PSF changes

The golden PSFs of `invglare regress` (one EXR per case, config in the header) change only
through `invglare regress --update --reason TEXT`, which appends an entry here: when, why,
which cases were rewritten and how far the stored PSFs were from the code just before the
update (metrics as in `reports/regression.md`; a new case has none). Cases whose stored PSF
was bit-identical to the recomputed one are listed as unchanged and not rewritten.
"""


def update_goldens(
    results: Sequence[CaseResult],
    golden_dir: str | os.PathLike[str],
    reason: str,
    *,
    now: Callable[[], dt.datetime] | None = None,
) -> list[str]:
    """Rewrite the goldens of the cases that differ and log the change in ``CHANGES.md``.

    **Arguments:**

    - `results`: from :func:`run_suite` (they hold the recomputed PSFs and models).
    - `golden_dir`: where the goldens and ``CHANGES.md`` live.
    - `reason`: why the stored PSFs change (required, recorded verbatim).
    - `now`: clock for the entry's date (tests).

    **Returns:** the names of the cases rewritten.

    **Raises:** `ConfigError` for an empty reason. Each file is written atomically;
    the log is written after the PSFs.
    """
    from invglare.files.atomic import write_text_atomic

    text = (reason or "").strip()
    if not text:
        raise ConfigError(
            "--update needs --reason TEXT saying why the stored PSFs change "
            "(it is recorded in tests/golden/CHANGES.md)"
        )
    folder = Path(golden_dir)
    rewritten, unchanged = [], []
    for r in results:
        if r.bit_identical and not r.config_changes:
            unchanged.append(r.case.name)
            continue
        write_golden(golden_path(folder, r.case), r.case, r.psf, r.model)
        rewritten.append(r.case.name)
    stamp = (now or (lambda: dt.datetime.now(dt.UTC)))().strftime("%Y-%m-%d %H:%M UTC")
    lines = [f"## {stamp}", "", f"Reason: {' '.join(text.split())}", ""]
    if rewritten:
        lines += [
            "| case | before | rel L2 | max err / peak | SSIM (log) | PSNR dB | EE diff |",
            "|---|---|---|---|---|---|---|",
        ]
        for r in results:
            if r.case.name in rewritten:
                before = {"pass": "passed", "fail": "failed"}.get(r.status, r.status)
                cells = " | ".join(metric_cells(r.metrics))
                lines.append(f"| {r.case.name} | {before} | {cells} |")
        lines.append("")
    else:
        lines += ["Nothing rewritten: every stored PSF was bit-identical.", ""]
    if unchanged:
        lines += [f"Unchanged (bit-identical, not rewritten): {', '.join(unchanged)}.", ""]
    log_path = folder / CHANGES_FILE
    old = log_path.read_text(encoding="utf-8") if log_path.exists() else _CHANGES_HEADER
    write_text_atomic(log_path, old.rstrip("\n") + "\n\n" + "\n".join(lines))
    return rewritten
