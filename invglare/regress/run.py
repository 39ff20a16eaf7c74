"""Running the golden suite: every case recomputed and compared with its stored PSF.

:func:`run_suite` recomputes every case from the registry
(:data:`~invglare.regress.cases.CASES`; the registry, not the golden's header, is the
source of truth: a header config that no longer matches is reported as a diagnosis) and
measures how far the new PSF is from the stored one
(:func:`~invglare.regress.compare.compare_psfs`). A different pixel scale or wavelength
list fails a case whatever the pixels say: on the FFT's native grid a 1 % larger pupil
gives the *same* array at a 1 % finer pixel scale.

**Example:**

```python
results = run_suite(golden_dir="tests/golden")
failed = [r.case.name for r in results if not r.passed]
```
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from invglare.errors import InputDataError, NumericalError
from invglare.regress.cases import CASES, Case, select_cases
from invglare.regress.compare import Metrics, compare_psfs, config_changes
from invglare.regress.goldens import golden_path, header_for

__all__ = ["CaseResult", "compute_case", "run_suite"]

log = logging.getLogger("invglare")


def _psf_of(model: Any, light_angle_deg: Any) -> Any:
    return model(light_angle_deg)  # None: the model's default direction (on axis)


_jitted_psf: Callable | None = None


def _jit_psf() -> Callable:
    # One jitted function for the whole process: a model of an already compiled structure
    # (the same case with a perturbed parameter, say) then reuses the compiled program.
    global _jitted_psf
    if _jitted_psf is None:
        import equinox as eqx

        _jitted_psf = eqx.filter_jit(_psf_of)
    return _jitted_psf


def compute_case(case: Case, *, x64: bool = False) -> tuple[np.ndarray, Any]:
    """Build the case's model and compute its PSF.

    **Arguments:**

    - `case`: the case.
    - `x64`: compute in float64 (for calibrating tolerances); the goldens are float32,
      which is forced otherwise, whatever the global JAX setting.

    **Returns:** ``(psf, model)``: the PSF as a numpy array, ``(npix, npix)`` or
    ``(npix, npix, 3)``, and the built model.

    **Raises:** whatever :func:`~invglare.config.model.build_model` raises for a bad
    config; `NumericalError` for a non-finite PSF.
    """
    import jax

    from invglare.config.model import build_model

    with jax.enable_x64(x64):
        model = build_model(case.config, source=f"regression case {case.name!r}")
        angle = case.light_angle_deg
        if angle is not None:
            angle = jax.numpy.asarray(angle, dtype=float)
        psf = np.asarray(_jit_psf()(model, angle))
    if not np.all(np.isfinite(psf)):
        raise NumericalError(f"regression case {case.name!r}: the PSF has non-finite values")
    return psf, model


@dataclasses.dataclass(eq=False)
class CaseResult:
    """The outcome of one case.

    **Fields:**

    - `case`: the case.
    - `status`: ``"pass"``, ``"fail"`` (metrics outside tolerance, or another pixel
      scale or wavelength list than the golden's), ``"missing"`` (no
      golden file) or ``"error"`` (the golden cannot be compared: unreadable, other shape).
    - `metrics`: the :class:`Metrics` (``None`` when missing or in error).
    - `failures`: the failing metrics, or the reason for ``"missing"`` / ``"error"``.
    - `config_changes`: dotted keys where the stored header config differs from the
      config the registry builds now (a diagnosis; the metrics decide).
    - `psf`, `reference`, `pixel_scale_deg`: the arrays compared (for figures).
    - `seconds`: time to build and compute the model (compilation included).
    - `model`: the built model (for writing a new golden).
    """

    case: Case
    status: str
    metrics: Metrics | None
    failures: list[str]
    config_changes: list[str]
    psf: np.ndarray
    reference: np.ndarray | None
    pixel_scale_deg: float
    seconds: float
    model: Any = None

    @property
    def passed(self) -> bool:
        return self.status == "pass"

    @property
    def bit_identical(self) -> bool:
        return (
            self.reference is not None
            and self.reference.shape == self.psf.shape
            and bool(np.array_equal(self.reference, self.psf.astype(np.float32)))
        )


def _run_case(case: Case, golden_dir: Path) -> CaseResult:
    from invglare.files.atomic import dumps_json
    from invglare.files.exr import read_exr

    t0 = time.perf_counter()
    psf, model = compute_case(case)
    seconds = time.perf_counter() - t0
    scale = float(model.pixel_scale_deg)
    path = golden_path(golden_dir, case)
    common = dict(case=case, psf=psf, pixel_scale_deg=scale, seconds=seconds, model=model)
    if not path.exists():
        why = f"no golden file {path}; create it with invglare regress --update --reason TEXT"
        return CaseResult(status="missing", metrics=None, failures=[why], config_changes=[],
                          reference=None, **common)  # fmt: skip
    try:
        golden = read_exr(path, allow_negative=True)
        metrics = compare_psfs(golden.data, psf, scale)
    except InputDataError as err:
        return CaseResult(status="error", metrics=None, failures=[str(err)], config_changes=[],
                          reference=None, **common)  # fmt: skip
    config, _, lams = header_for(case, model)
    # Round-trip through JSON so that tuples and numpy scalars compare like the header.
    current = json.loads(dumps_json(config, indent=None))
    changes = config_changes(golden.config or {}, current)
    failures = metrics.failures(case.tolerance)
    # The sampling gives the pixels their meaning: the same array at another pixel scale
    # (a 1 % larger pupil on the FFT's native grid, say) or other wavelengths is another PSF.
    # 1e-5: the header's float32 attributes come back rounded (see _config_changes).
    if golden.pixel_scale_deg is None or not math.isclose(
        golden.pixel_scale_deg, scale, rel_tol=1e-5
    ):
        failures.append(f"pixel scale {golden.pixel_scale_deg} -> {scale:.7g} deg/px")
    stored_lams = golden.wavelengths_nm or ()
    if len(stored_lams) != len(lams) or not np.allclose(stored_lams, lams, rtol=1e-5):
        failures.append(f"wavelengths {list(stored_lams)} -> {lams} nm")
    return CaseResult(
        status="fail" if failures else "pass",
        metrics=metrics,
        failures=failures,
        config_changes=changes,
        reference=golden.data,
        **common,
    )


def run_suite(
    names: Iterable[str] = (),
    golden_dir: str | os.PathLike[str] = "tests/golden",
    *,
    cases: Sequence[Case] = CASES,
    progress: bool | None = None,
) -> list[CaseResult]:
    """Recompute the selected cases and compare each with its golden file.

    **Arguments:**

    - `names`: case names (default: all of `cases`).
    - `golden_dir`: the folder of golden EXRs.
    - `cases`: the registry to draw from (tests pass perturbed copies).
    - `progress`: show a tqdm bar (``None``: only on a terminal).

    **Returns:** one :class:`CaseResult` per case, in registry order. A missing or
    unreadable golden gives a result with that status rather than an exception, so
    one broken file does not hide the others.

    **Raises:** `ConfigError` for an unknown case name; a case whose config no longer
    builds raises its own error (that is a failure of the code, not of the physics).
    """
    from tqdm import tqdm

    chosen = select_cases(names, cases)
    results = []
    disable = None if progress is None else not progress
    for case in tqdm(chosen, desc="regress", unit="case", disable=disable):
        result = _run_case(case, Path(golden_dir))
        log.debug("%s: %s in %.2f s", case.name, result.status, result.seconds)
        results.append(result)
    return results
