"""Golden regression: every model and mode, recomputed and compared with stored reference PSFs.

A *case* is a small reference configuration of a forward model (a model config as in
:mod:`invglare.config.model`, plus a light direction for position-dependent
masking). Its PSF was computed once, in float32 on the CPU, and stored as an EXR file
``<golden_dir>/<case>.exr`` whose header holds the full model config
(``invglareConfig``), the pixel scale, the wavelengths and the case's name and light
angle. :func:`run_suite` recomputes every case from the registry below (the
registry, not the header, is the source of truth: a header config that no longer
matches is reported as a diagnosis) and measures how far the new PSF is from the
stored one. A different pixel scale or wavelength list fails a case whatever the
pixels say: on the FFT's native grid a 1 % larger pupil gives the *same* array at a
1 % finer pixel scale.

**Metrics** (``ref`` the stored PSF, ``new`` the recomputed one, ``peak = max(ref)``;
RGB PSFs are compared over all three channels):

- `rel_l2`: ``‖new − ref‖₂ / ‖ref‖₂``;
- `max_err`: ``max |new − ref| / peak``;
- `ssim_log`: SSIM (scikit-image `structural_similarity`, 7×7 window, data range 1) of
  the **log-scaled** images ``clip(1 + log10(x / peak) / 6, 0, 1)`` (six decades below
  the reference peak, both images on the same scale);
- `psnr_db`: PSNR (scikit-image `peak_signal_noise_ratio`) of the linear images, data
  range ``peak``; ``inf`` for identical images;
- `ee_diff`: ``max_r |EE_new(r) − EE_ref(r)|``, the encircled energy as a fraction of
  the unit-energy PSF at radii 1, 2, 4, … px up to the half-width, per channel.

SSIM is taken on the log-scaled images because a PSF spans six or more decades and
its glare (streaks, halos, the ciliary corona) lives far below the peak, where a
linear SSIM would see nothing; the linear metrics (L2, max error, PSNR) watch the
core.

**Tolerances.** Per case (:class:`Tolerance`), set for float32 reproducibility on a
CPU: what two correct implementations may differ by (a different XLA or FFT build,
other BLAS blocking in the matrix Fourier transform, a reordered sum). Calibration:
every case was computed in float32 and in float64 (for the eyes, whose random draws
differ between the two precisions, the float32 field propagated in float64), and the
bounds give at least ten times the float32 error so measured. Worst measured, all cases
but Fresnel: rel L2 1.7e-6, max error 1.3e-6 of the peak, PSNR 157 dB, EE 3e-6, SSIM
1 − 1e-9; bounds 2e-5, 1.5e-5, 135 dB, 3e-5, 0.99999. The Fresnel case carries the
float32 round-off of an ~80 rad quadratic phase (measured rel L2 3.3e-6, max error
9.7e-6, PSNR 115 dB) and has looser bounds (5e-5, 1e-4, 95 dB). Every bound sits far
below what a physical change does: a 1 % larger pupil moves rel L2 by 1.3-1.6 % and
SSIM (log) to 0.76-0.86 (MFT aperture, eye). A GPU
(TF32 matrix products, other FFTs) is not expected to meet them.

**Coverage.** ``AperturePSF`` by FFT and by MFT, with the Fresnel term, monochrome,
spectral-exact and spectral-scaled; the Kakimoto eye with fixed and position-dependent
masking in ``paper_rgb`` and spectral colour; the Kakimoto camera with a cross-screen
filter; one frame of the temporal model of Ritschel et al. (``models.temporal``: Fresnel
term, scaled spectral copies) at a fixed time and key (its dynamics are pure functions
of time and key, so a frame is reproducible).

**Updating.** :func:`update_goldens` rewrites the stored PSFs of the cases that
differ (or are missing) and appends to ``<golden_dir>/CHANGES.md`` the date, the reason
and the metrics of the stored PSFs *before* the update, so every change of the physics
is recorded with its size.

**Example:**

```python
results = run_suite(golden_dir="tests/golden")
failed = [r.case.name for r in results if not r.passed]
write_report(results, "reports")
```
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import logging
import math
import os
import platform
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from jaxtyping import Float

from invglare.errors import ConfigError, InputDataError, NumericalError

__all__ = [
    "CASES",
    "CHANGES_FILE",
    "DEFAULT_TOLERANCE",
    "Case",
    "CaseResult",
    "Metrics",
    "Tolerance",
    "compare_psfs",
    "compute_case",
    "golden_path",
    "log_scaled",
    "run_suite",
    "select_cases",
    "update_goldens",
    "write_golden",
    "write_report",
]

log = logging.getLogger("invglare")

#: Name of the change log kept next to the golden files.
CHANGES_FILE = "CHANGES.md"
#: Decades below the reference peak shown by the log-scaled images (SSIM, figures).
LOG_DECADES = 6.0
#: Rec. 709 / sRGB luminance weights, for the figures of RGB PSFs.
_LUMA = np.array([0.2126, 0.7152, 0.0722])


# ------------------------------------------------------------------------------ registry


@dataclasses.dataclass(frozen=True)
class Tolerance:
    """Largest accepted differences of one case (see the module docstring for the metrics).

    **Fields:** `rel_l2`, `max_err` (relative to the reference peak), `ee_diff`
    (absolute, fraction of the light) are upper bounds; `ssim_log` and `psnr_db` are
    lower bounds.
    """

    rel_l2: float = 2e-5
    max_err: float = 1.5e-5
    ssim_log: float = 0.99999
    psnr_db: float = 135.0
    ee_diff: float = 3e-5
    why: str = "float32 round-off on a CPU (measured ≤ 1.7e-6 rel L2), ≥ 10x headroom"


#: Tolerances of most cases (float32 CPU reproducibility; see the module docstring).
DEFAULT_TOLERANCE = Tolerance()
#: The Fresnel term's quadratic phase reaches ~80 rad at the window's edge, where float32
#: carries ~5e-6 rad of round-off: its PSF is ~3x less reproducible (measured rel L2
#: 3.3e-6, max error 9.7e-6 of the peak, PSNR 115 dB against float64).
FRESNEL_TOLERANCE = Tolerance(
    rel_l2=5e-5,
    max_err=1e-4,
    psnr_db=95.0,
    why="float32 round-off of the Fresnel phase (measured ≤ 3.3e-6 rel L2), ≥ 10x headroom",
)


@dataclasses.dataclass(frozen=True)
class Case:
    """One reference configuration.

    **Fields:**

    - `name`: file stem of the golden EXR and the name on the command line.
    - `description`: one line saying what it exercises.
    - `config`: the model config (the TOML tables as a dict), for
      :func:`invglare.config.model.build_model`.
    - `light_angle_deg`: ``(x, y)`` light direction for a Kakimoto model (what
      position-dependent masking depends on); ``None`` for an ``AperturePSF``.
    - `tolerance`: the case's :class:`Tolerance`.
    """

    name: str
    description: str
    config: dict[str, Any]
    light_angle_deg: tuple[float, float] | None = None
    tolerance: Tolerance = DEFAULT_TOLERANCE


def _aperture(shapes: list[dict], output: dict, spectrum: dict, **model: Any) -> dict[str, Any]:
    table = {"kind": "aperture", "focal_length_mm": 17.0, **model, "shapes": shapes}
    return {"model": table, "output": output, "spectrum": spectrum}


_DISK_4MM = {"kind": "disk", "diameter_mm": 4.0}
_HEXAGON = {
    "kind": "polygon",
    "n_blades": 6,
    "diameter_mm": 6.25,
    "rotation_deg": 15.0,
    "rounding": 0.2,
}
_LASH_BAR = {"kind": "capsule", "start_mm": [-3.2, 1.1], "end_mm": [3.2, 1.6], "thickness_mm": 0.1}

# Two small eyes at 128 aperture pixels. Compilation dominates their cost and grows with
# every kind of component, so each eye carries what its masking mode is about: the fixed
# eye the structures inside the eye (particles, lens-fibre gratings) under the lids; the
# position-dependent eye the obstacles that move with the light (lids, both lash rows).
_LASHES_UPPER = {
    "count": 24.0,
    "n_max": 28,
    "angular_spread_deg": 12.0,
    "thickness_mm": 0.07,
    "length_mm": 2.5,
    "curvature_per_mm": 0.05,
    "root_span_mm": 7.0,
}
_LIDS = {"upper_opening_mm": 1.2, "lower_opening_mm": 1.4, "curvature_per_mm": 0.04}
_EYE_INNER = {
    "seed": 11,
    "pupil": {"diameter_mm": 3.0, "ellipticity": 0.05, "rotation_deg": 20.0},
    "lids": _LIDS,
    "particles": [{"region": "cornea", "count": 60.0, "n_max": 64, "radius_mean_mm": 0.02}],
    # The annulus lies inside the 3 mm pupil (the default 2-3.5 mm one would be hidden).
    "gratings": {
        "count": 12.0,
        "n_max": 12,
        "spacing_mm": 0.08,
        "line_thickness_mm": 0.03,
        "inner_radius_mm": 0.6,
        "outer_radius_mm": 1.4,
    },
}
_EYE_OBSTACLES = {
    "seed": 5,
    "pupil": {"diameter_mm": 3.0},
    "lids": _LIDS,
    "lashes_upper": _LASHES_UPPER,
    "lashes_lower": {
        "count": 10.0,
        "n_max": 12,
        "angular_spread_deg": 15.0,
        "thickness_mm": 0.06,
        "length_mm": 2.0,
        "curvature_per_mm": -0.05,
        "root_span_mm": 6.0,
    },
}


def _eye(eye: dict, masking: str, colour: str, output: dict, spectrum: dict) -> dict[str, Any]:
    table = {
        "kind": "eye",
        "focal_length_mm": 17.0,
        "obstacle_distance_mm": 8.0,
        "masking": masking,
        "colour": colour,
        "max_light_angle_deg": 10.0,
        "aperture_npix": 128,
        "eye": eye,
    }
    return {"model": table, "output": output, "spectrum": spectrum}


#: The suite. Output grids are at most 128 x 128 so that the whole suite runs in well
#: under a minute on two CPU cores.
CASES: tuple[Case, ...] = (
    Case(
        "aperture_fft_mono",
        "4 mm disk (Airy pattern), FFT at its native pixel scale, 550 nm",
        _aperture(
            [_DISK_4MM],
            {"npix": 128},
            {"wavelengths_nm": 550.0},
            aperture_npix=64,
            method="fft",
        ),
    ),
    Case(
        "aperture_mft_mono",
        "rounded 6-blade diaphragm crossed by a bar, MFT at 0.003 deg/px, 550 nm",
        _aperture(
            [_HEXAGON, {**_LASH_BAR, "role": "block"}],
            {"npix": 128, "pixel_scale_deg": 0.003},
            {"wavelengths_nm": 550.0},
            aperture_npix=128,
            method="mft",
        ),
    ),
    Case(
        "aperture_fresnel",
        "1 mm pupil and a lash, Fresnel term of Ritschel et al. eq. 3, FFT, 575 nm",
        _aperture(
            [
                {"kind": "disk", "diameter_mm": 1.0},
                {
                    "kind": "capsule",
                    "start_mm": [-0.6, 0.1],
                    "end_mm": [0.6, 0.25],
                    "thickness_mm": 0.03,
                    "role": "block",
                },
            ],
            {"npix": 128},
            {"wavelengths_nm": 575.0},
            aperture_npix=128,
            propagation="fresnel",
        ),
        tolerance=FRESNEL_TOLERANCE,
    ),
    Case(
        "aperture_spectral_exact",
        "rounded 6-blade diaphragm, 8 wavelengths 400-700 nm each by MFT, linear sRGB (D65)",
        _aperture(
            [_HEXAGON],
            {"npix": 128, "pixel_scale_deg": 0.003},
            {"wavelengths_nm": "400:700:8", "spectral": "exact", "illuminant": "D65"},
            aperture_npix=128,
            method="mft",
        ),
    ),
    Case(
        "aperture_spectral_scaled",
        "rounded 6-blade diaphragm, 8 wavelengths as scaled copies of one FFT PSF (Ritschel)",
        _aperture(
            [_HEXAGON],
            {"npix": 128},
            {"wavelengths_nm": "400:700:8", "spectral": "scaled", "illuminant": "D65"},
            aperture_npix=128,
        ),
    ),
    Case(
        "eye_fixed_paper_rgb",
        "Kakimoto eye (elliptic pupil, particles, gratings, lids), fixed mask, 680/530/460 nm "
        "as RGB",
        _eye(_EYE_INNER, "fixed", "paper_rgb", {"npix": 128}, {}),
    ),
    Case(
        "eye_position_spectral",
        "Kakimoto eye (lids, both lash rows), mask moved for a light at (4, -2) deg, "
        "6 wavelengths 420-680 nm exact by MFT",
        _eye(
            _EYE_OBSTACLES,
            "position",
            "spectral",
            {"npix": 128, "pixel_scale_deg": 0.004},
            {"wavelengths_nm": "420:680:6", "spectral": "exact"},
        ),
        light_angle_deg=(4.0, -2.0),
    ),
    Case(
        "camera_cross_screen",
        "Kakimoto camera: 6-blade f/8 50 mm diaphragm behind a cross-screen filter, paper RGB",
        {
            "model": {
                "kind": "camera",
                "obstacle_distance_mm": 20.0,
                "masking": "fixed",
                "colour": "paper_rgb",
                "aperture_npix": 128,
                "camera": {
                    "diaphragm": {
                        "n_blades": 6,
                        "f_number": 8.0,
                        "focal_length_mm": 50.0,
                        "rotation_deg": 10.0,
                    },
                    "cross_screen": {
                        "angles_deg": [0.0, 90.0],
                        "spacing_mm": 0.4,
                        "duty_cycle": 0.2,
                    },
                },
            },
            "output": {"npix": 128},
        },
    ),
    Case(
        "temporal_frame",
        "temporal eye (Ritschel): frame 0 of key 3 adapted to 10 cd/m^2, lids, lashes, lens "
        "particles and gratings, Fresnel at 575 nm, 8 scaled copies 400-700 nm",
        {
            "model": {
                "kind": "temporal",
                "aperture_npix": 128,
                "focal_length_mm": 1200.0,
                "seed": 3,
                "field_luminance_cd_m2": 10.0,
                "eye": {
                    "seed": 5,
                    "pupil": {"diameter_mm": 6.0},
                    "lids": _LIDS,
                    "lashes_upper": _LASHES_UPPER,
                    "particles": [
                        {
                            "region": "lens_nucleus",
                            "count": 40.0,
                            "n_max": 40,
                            "radius_mean_mm": 0.04,
                        },
                    ],
                    "gratings": {
                        "count": 12.0,
                        "n_max": 12,
                        "spacing_mm": 0.08,
                        "line_thickness_mm": 0.03,
                    },
                },
            },
            "output": {"npix": 128},
            "spectrum": {"wavelengths_nm": "400:700:8"},
        },
        tolerance=FRESNEL_TOLERANCE,
    ),
)


def select_cases(names: Iterable[str] = (), cases: Sequence[Case] = CASES) -> list[Case]:
    """The cases named (all of `cases` when `names` is empty), in registry order.

    **Raises:** `ConfigError` naming an unknown case and listing the valid ones.
    """
    wanted = list(names)
    known = {c.name: c for c in cases}
    unknown = [n for n in wanted if n not in known]
    if unknown:
        raise ConfigError(f"unknown regression case {unknown[0]!r}; cases: {', '.join(known)}")
    if not wanted:
        return list(cases)
    return [c for c in cases if c.name in wanted]


def golden_path(golden_dir: str | os.PathLike[str], case: Case) -> Path:
    """Where the golden PSF of `case` lives: ``<golden_dir>/<name>.exr``."""
    return Path(golden_dir) / f"{case.name}.exr"


# ------------------------------------------------------------------------------ computing


def _psf_of(model: Any, light_angle_deg: Any) -> Any:
    return model() if light_angle_deg is None else model(light_angle_deg)


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


def _header_for(case: Case, model: Any) -> tuple[dict[str, Any], dict[str, Any], list[float]]:
    from invglare.config.model import model_to_config

    config = model_to_config(model)
    attrs: dict[str, Any] = {
        "regressionCase": case.name,
        "regressionDescription": case.description,
        "propagationMethod": model.propagator.method,
        "psfNormalisation": "fraction of the transmitted power per pixel",
    }
    if case.light_angle_deg is not None:
        attrs["lightAngleDeg"] = [float(a) for a in case.light_angle_deg]
    lams = [float(w) for w in np.asarray(model.spectrum.wavelengths_nm)]
    return config, attrs, lams


def write_golden(path: str | os.PathLike[str], case: Case, psf: np.ndarray, model: Any) -> Path:
    """Store `psf` as the golden of `case` (float32 EXR, config and case in the header)."""
    from invglare.files.exr import write_exr

    config, attrs, lams = _header_for(case, model)
    return write_exr(
        path,
        np.asarray(psf, dtype=np.float32),
        pixel_scale_deg=float(model.propagator.output.pixel_scale_deg),
        wavelengths_nm=lams,
        config=config,
        attrs=attrs,
    )


# ------------------------------------------------------------------------------ metrics


@dataclasses.dataclass(frozen=True)
class Metrics:
    """Differences of a recomputed PSF from its golden (module docstring: definitions)."""

    rel_l2: float
    max_err: float
    ssim_log: float
    psnr_db: float
    ee_diff: float

    def failures(self, tol: Tolerance) -> list[str]:
        """The metrics outside `tol`, as ``"rel_l2 1.2e-3 > 3e-5"`` strings."""
        out = []
        for name, value, limit, worse in (
            ("rel_l2", self.rel_l2, tol.rel_l2, self.rel_l2 > tol.rel_l2),
            ("max_err", self.max_err, tol.max_err, self.max_err > tol.max_err),
            ("ssim_log", self.ssim_log, tol.ssim_log, self.ssim_log < tol.ssim_log),
            ("psnr_db", self.psnr_db, tol.psnr_db, self.psnr_db < tol.psnr_db),
            ("ee_diff", self.ee_diff, tol.ee_diff, self.ee_diff > tol.ee_diff),
        ):
            # NaN compares False everywhere: treat it as a failure explicitly.
            if worse or math.isnan(value):
                sign = "<" if name in ("ssim_log", "psnr_db") else ">"
                out.append(f"{name} {value:.3g} {sign} {limit:g}")
        return out


def log_scaled(
    image: Float[np.ndarray, "*shape"], peak: float, decades: float = LOG_DECADES
) -> Float[np.ndarray, "*shape"]:
    """``clip(1 + log10(image / peak) / decades, 0, 1)``: a PSF as a [0, 1] image.

    **Example:** ``log_scaled(psf, psf.max())`` maps the peak to 1 and 1e-6 of it to 0.
    """
    ratio = np.maximum(np.asarray(image, dtype=np.float64) / peak, 10.0 ** (-2 * decades))
    return np.clip(1.0 + np.log10(ratio) / decades, 0.0, 1.0)


def _ee_radii_px(npix: int) -> np.ndarray:
    radii = [1.0]
    while radii[-1] * 2 < npix // 2 - 1:
        radii.append(radii[-1] * 2)
    radii.append(float(npix // 2 - 1))
    return np.asarray(radii)


def compare_psfs(
    reference: Float[np.ndarray, "h w *c"],
    new: Float[np.ndarray, "h w *c"],
    pixel_scale_deg: float,
) -> Metrics:
    """The five metrics of `new` against `reference` (module docstring).

    **Raises:** `InputDataError` when the shapes differ (a changed grid is a failure
    of its own, not something to interpolate over).

    **Example:**

    ```python
    m = compare_psfs(golden, psf, 0.004)
    m.failures(DEFAULT_TOLERANCE)   # [] when it passes
    ```
    """
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    from invglare.reference.profiles import encircled_energy

    ref = np.asarray(reference, dtype=np.float64)
    cur = np.asarray(new, dtype=np.float64)
    if ref.shape != cur.shape:
        raise InputDataError(
            f"the recomputed PSF has shape {cur.shape} but the golden has {ref.shape}"
        )
    peak = float(np.max(ref))
    if not peak > 0:
        raise InputDataError(f"the golden PSF has no positive value (max {peak:g})")
    diff = cur - ref
    rel_l2 = float(np.linalg.norm(diff) / np.linalg.norm(ref))
    max_err = float(np.max(np.abs(diff)) / peak)
    rgb = ref.ndim == 3
    ssim = float(
        structural_similarity(
            log_scaled(ref, peak),
            log_scaled(cur, peak),
            data_range=1.0,
            channel_axis=-1 if rgb else None,
        )
    )
    if np.any(diff):
        psnr = float(peak_signal_noise_ratio(ref, cur, data_range=peak))
    else:
        psnr = math.inf  # skimage divides by a zero MSE (and warns) for identical images
    radii = _ee_radii_px(ref.shape[0]) * pixel_scale_deg
    planes_ref = ref if rgb else ref[..., None]
    planes_cur = cur if rgb else cur[..., None]
    # Channels first for the batched encircled energy; total=1: the PSFs are fractions.
    ee_ref, ee_cur = (
        np.asarray(encircled_energy(np.moveaxis(p, -1, 0), pixel_scale_deg, radii, total=1.0))
        for p in (planes_ref, planes_cur)
    )
    ee = float(np.max(np.abs(ee_cur - ee_ref)))
    return Metrics(rel_l2=rel_l2, max_err=max_err, ssim_log=ssim, psnr_db=psnr, ee_diff=ee)


# ------------------------------------------------------------------------------ the suite


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


def _config_changes(stored: Any, current: Any, prefix: str = "") -> list[str]:
    """Dotted keys where two JSON-like configs differ (numbers to a relative 1e-5).

    1e-5 rather than float32's 6e-8: EXR float attributes come back through a decimal
    rounding that, once colour-science has set numpy's legacy print options, keeps only
    six significant digits.
    """
    if isinstance(stored, dict) and isinstance(current, dict):
        out = []
        for key in sorted(set(stored) | set(current), key=str):
            where = f"{prefix}.{key}" if prefix else str(key)
            if key not in stored or key not in current:
                out.append(where)
            else:
                out.extend(_config_changes(stored[key], current[key], where))
        return out
    if isinstance(stored, list) and isinstance(current, list):
        if len(stored) != len(current):
            return [prefix]
        out = []
        for i, (a, b) in enumerate(zip(stored, current, strict=True)):
            out.extend(_config_changes(a, b, f"{prefix}[{i}]"))
        return out
    if isinstance(stored, int | float) and isinstance(current, int | float):
        same = math.isclose(float(stored), float(current), rel_tol=1e-5, abs_tol=1e-12)
        return [] if same else [prefix]
    return [] if stored == current else [prefix]


def _run_case(case: Case, golden_dir: Path) -> CaseResult:
    from invglare.files.atomic import dumps_json
    from invglare.files.exr import read_exr

    t0 = time.perf_counter()
    psf, model = compute_case(case)
    seconds = time.perf_counter() - t0
    scale = float(model.propagator.output.pixel_scale_deg)
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
    config, _, lams = _header_for(case, model)
    # Round-trip through JSON so that tuples and numpy scalars compare like the header.
    current = json.loads(dumps_json(config, indent=None))
    changes = _config_changes(golden.config or {}, current)
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


# ------------------------------------------------------------------------------ updating


def _metric_cells(m: Metrics | None) -> list[str]:
    if m is None:
        return ["–"] * 5
    psnr = "inf" if math.isinf(m.psnr_db) else f"{m.psnr_db:.1f}"
    return [f"{m.rel_l2:.2e}", f"{m.max_err:.2e}", f"{m.ssim_log:.6f}", psnr, f"{m.ee_diff:.2e}"]


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
                cells = " | ".join(_metric_cells(r.metrics))
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


# ------------------------------------------------------------------------------ reporting


def _display(image: np.ndarray) -> np.ndarray:
    """Luminance of an RGB PSF (what the figures show); a mono PSF as it is."""
    return image @ _LUMA if image.ndim == 3 else image


#: Difference images: log10 |new − golden| / peak is shown from this floor up.
DIFF_FLOOR_LOG10 = -12.0


def _figure(result: CaseResult, path: Path) -> None:
    """Write ``[golden | recomputed | difference]`` as one PNG, 2x magnified, no axes.

    Golden and recomputed: ``log10(PSF / peak)`` from -6 to 0 (magma; luminance of an
    RGB PSF). Difference: ``log10(|new − golden| / peak)`` from -12 to 0 (viridis). Plain
    images rather than a plotted figure: matplotlib's axes cost seconds per case.
    """
    from matplotlib import colormaps

    from invglare.files.images import write_png

    new = _display(np.asarray(result.psf, dtype=np.float64))
    ref = None if result.reference is None else _display(np.asarray(result.reference, np.float64))
    peak = float(np.max(ref if ref is not None else new))
    blank = np.full((*new.shape, 3), 0.5)
    magma, viridis = colormaps["magma"], colormaps["viridis"]

    def shade(img):
        return magma(log_scaled(img, peak))[..., :3]

    panels = [blank if ref is None else shade(ref), shade(new), blank]
    if ref is not None and ref.shape == new.shape:
        err = np.log10(np.maximum(np.abs(new - ref) / peak, 10.0**DIFF_FLOOR_LOG10))
        panels[2] = viridis((err - DIFF_FLOOR_LOG10) / -DIFF_FLOOR_LOG10)[..., :3]
    gap = np.ones((new.shape[0], 4, 3))
    strip = np.concatenate([panels[0], gap, panels[1], gap, panels[2]], axis=1)
    # Row 0 of a PSF is the bottom of the field (y up): flip for the image.
    strip = np.repeat(np.repeat(strip[::-1], 2, axis=0), 2, axis=1)
    write_png(path, strip)


def _environment() -> str:
    import jax

    import invglare

    version = getattr(invglare, "__version__", "unknown")
    devices = ", ".join(sorted({d.platform for d in jax.devices()}))
    return (
        f"invglare {version}, JAX {jax.__version__} on {devices}, Python "
        f"{platform.python_version()}, {platform.machine()} {platform.system()}"
    )


def write_report(
    results: Sequence[CaseResult],
    out_dir: str | os.PathLike[str] = "reports",
    *,
    updated: Sequence[str] = (),
    golden_dir: str | os.PathLike[str] = "tests/golden",
) -> Path:
    """Write ``<out_dir>/regression.md`` and a difference figure per case (``regression/``).

    **Returns:** the markdown path. Every file is written atomically.
    """
    from invglare.files.atomic import write_text_atomic

    out = Path(out_dir)
    fig_dir = out / "regression"
    for r in results:
        _figure(r, fig_dir / f"{r.case.name}.png")
    n_fail = sum(not r.passed for r in results)
    stamp = dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    verdict = "all cases pass" if n_fail == 0 else f"{n_fail} of {len(results)} case(s) FAIL"
    if updated:
        verdict += f" before the update; rewritten: {', '.join(updated)}"
    total = sum(r.seconds for r in results)
    lines = [
        "# Golden regression",
        "",
        f"`invglare regress`, {stamp}: **{verdict}** ({len(results)} cases, "
        f"{total:.1f} s of model time). {_environment()}. Goldens: `{golden_dir}`.",
        "",
        "| case | status | rel L2 | max err / peak | SSIM (log) | PSNR dB | EE diff | time s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        cells = " | ".join(_metric_cells(r.metrics))
        name = f"[{r.case.name}](regression/{r.case.name}.png)"
        status = r.status.upper() if r.status != "pass" else "pass"
        lines.append(f"| {name} | {status} | {cells} | {r.seconds:.1f} |")
    lines += ["", "Tolerances (a case fails when any metric is outside its bound):", ""]
    lines += [
        "| case | rel L2 ≤ | max err ≤ | SSIM ≥ | PSNR ≥ dB | EE diff ≤ | basis |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in results:
        t = r.case.tolerance
        lines.append(
            f"| {r.case.name} | {t.rel_l2:g} | {t.max_err:g} | {t.ssim_log:g} | "
            f"{t.psnr_db:g} | {t.ee_diff:g} | {t.why} |"
        )
    problems = [r for r in results if r.failures or r.config_changes]
    if problems:
        lines += ["", "## Details", ""]
        for r in problems:
            if r.failures:
                lines.append(f"- **{r.case.name}** ({r.status}): {'; '.join(r.failures)}")
            if r.config_changes:
                keys = ", ".join(r.config_changes[:8])
                more = f" and {len(r.config_changes) - 8} more" if len(r.config_changes) > 8 else ""
                lines.append(
                    f"- **{r.case.name}**: the stored header config differs from the "
                    f"registry's at {keys}{more}"
                )
    lines += [
        "",
        "## Cases",
        "",
        *[f"- `{r.case.name}`: {r.case.description}." for r in results],
        "",
        "## Metrics",
        "",
        "- rel L2: `‖new − golden‖₂ / ‖golden‖₂` over all pixels and channels;",
        "- max err / peak: `max |new − golden|` over the golden's peak;",
        "- SSIM (log): scikit-image `structural_similarity` (7×7 window, data range 1) of the",
        "  log-scaled images `clip(1 + log10(x / peak) / 6, 0, 1)` — six decades below the",
        "  golden's peak, because a PSF's glare lives far below its peak where a linear SSIM",
        "  sees nothing;",
        "- PSNR: scikit-image `peak_signal_noise_ratio` of the linear images, data range = peak",
        "  (`inf` for identical images);",
        "- EE diff: the largest difference of encircled energy (fraction of the unit-energy PSF)",
        "  at radii 1, 2, 4, … px up to the half-width, per channel.",
        "",
        "Difference images (`regression/<case>.png`, click a case): left the golden, middle the",
        "recomputed PSF, as `log10(PSF / peak)` from −6 to 0 (magma; luminance for RGB, y up);",
        "right `log10(|recomputed − golden| / peak)` from −12 to 0 (viridis; all dark when the",
        "two are bit-identical).",
        "",
        "The temporal model (Ritschel et al.) is covered by one frame at a fixed time and key",
        "(`temporal_frame`).",
        "",
    ]
    path = out / "regression.md"
    write_text_atomic(path, "\n".join(lines))
    return path
