"""Fit configs whose target is a reference glare function: the CIE's, or a PSF / GSF file.

``invglare fit`` reads a config with a ``[reference]`` table through
:func:`load_reference_fit` (a config with ``[target]`` is a photo fit, see
:mod:`invglare.config.fit`). The eye model's radially averaged GSF is fitted to the
reference over a range of angles, in log units (:mod:`invglare.cie_study.fit` says
why and with which eye). Relative paths are relative to the config file.

```toml
[fit]
name = "cie_A50_p1"                  # default: the file's stem
out_dir = "../runs/cie_A50_p1"    # default: runs/NAME under the current folder

[reference]                          # exactly one of:
cie = { age = 50.0, pigmentation = 1.0 }   # the CIE disability-glare GSF (CIE 135/1)
# file = "my_psf.exr"                # a 2-D PSF with pixelScaleDeg: energy per pixel as a
#                                    #   fraction of the light entering (as invglare writes)
# file = "my_gsf.csv"                # a 1-D GSF: lines of theta_deg, value (sr^-1)

[eye]                                # the fitted eye (defaults: CieFitSetup)
pupil_diameter_mm = 3.0
wavelengths_nm = [460.0, 490.0, 520.0, 550.0, 580.0, 610.0, 640.0]
aperture_npix = 256                  # sets the largest angle the model covers
npix = 108
pixel_scale_deg = 0.02
seed = 0                             # the particles' random draw

[[population]]                       # the fitted particles (default: the two of setup.py)
region = "cornea"                    # cornea, lens_nucleus or vitreous
count_max = 3000                     # pool size and the count's upper bound
count_init = 800.5                   # not an integer: a relaxed count has no slope there
radius_min_mm = 0.002
radius_max_mm = 0.02
radius_init_mm = 0.006
radius_spread = 0.3                  # log-normal sigma, fixed
region_radius_mm = 1.6

[range]
theta_min_deg = 0.1
theta_max_deg = 0.9                  # default: the largest the model's sampling covers
n_bins = 20                          # logarithmic annuli

[solver]
n_starts = 3
max_steps = 60
```

**Example:**

```python
setup = load_reference_fit("fits/cie_A50_p1.toml")
result = setup.run()                 # a CieFitResult
```
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np

from invglare.aperture.eye import REGIONS
from invglare.cie_study.annuli import RadialBins, annulus_mean
from invglare.cie_study.fit import CieFitResult, fit_cie, fit_radial_gsf
from invglare.cie_study.setup import CieFitSetup, Population
from invglare.config.fit import is_reference_fit, read_fit_section
from invglare.config.section import Section, check_sections
from invglare.errors import ConfigError, InputDataError, PhysicsRangeError
from invglare.files.toml import load_toml
from invglare.reference.profiles import RadialTable, ReferenceImage, load_reference_psf

SECTIONS = ("fit", "reference", "eye", "population", "range", "solver")

_EYE_KEYS = {
    "pupil_diameter_mm": float,
    "aperture_npix": int,
    "npix": int,
    "pixel_scale_deg": float,
    "seed": int,
}


@dataclasses.dataclass(frozen=True, eq=False)
class ReferenceFit:
    """A loaded reference-fit config: what to fit, to what, and where the report goes.

    **Fields:** `name`; `out_dir`; `config_path`; `setup` (the eye, range and solver);
    `cie` (``(age, pigmentation)``) or `reference` (the file's
    :class:`~invglare.reference.profiles.RadialTable` of a 1-D file, or `image` and
    `image_scale_deg` of a 2-D one) with `reference_path`.
    """

    name: str
    out_dir: Path
    config_path: Path
    setup: CieFitSetup
    cie: tuple[float, float] | None = None
    reference: RadialTable | None = None
    reference_path: Path | None = None
    image: np.ndarray | None = None
    image_scale_deg: float | None = None

    def describe(self) -> str:
        """The reference in words, for logs and the report."""
        if self.cie is not None:
            age, pig = self.cie
            return f"the CIE disability-glare GSF, age {age:g}, pigmentation {pig:g}"
        if self.image is not None:
            n = self.image.shape[0]
            return f"`{self.reference_path}` ({n}x{n} PSF at {self.image_scale_deg:g} deg/px)"
        return f"`{self.reference_path}` ({self.reference.source})"

    def target(self, bins: RadialBins) -> np.ndarray:
        """The reference GSF (sr⁻¹) averaged over each annulus, like the model's.

        A 2-D reference is averaged over the same annuli on its own pixels (energy per
        pixel over the pixel's solid angle), so a reference on the model's grid gives
        exactly the model's statistic; a table is averaged at the model's pixel centres.
        """
        if self.image is not None:
            scale = float(self.image_scale_deg)
            lo, hi = float(bins.edges_deg[0]), float(bins.edges_deg[-1])
            own = _image_bins(self.image, scale, lo, hi, bins.n_bins, self.reference_path)
            return np.asarray(own.mean(self.image)) / math.radians(scale) ** 2
        if self.reference is None:
            raise ConfigError("a CIE reference is fitted by fit_cie, not through target()")
        return annulus_mean(self.reference, bins)

    def run(self, progress: bool | None = None) -> CieFitResult:
        """Fit the eye to the reference (float64, minutes). **Returns:** the best start."""
        if self.cie is not None:
            return fit_cie(*self.cie, self.setup, progress=progress)
        return fit_radial_gsf(self.target, self.setup, label=self.name, progress=progress)


def _square_psf(image: ReferenceImage) -> np.ndarray:
    """The reference image's luminance plane, cropped to the largest square about its centre
    pixel ``(H // 2, W // 2)`` (where the model puts the source)."""
    psf = np.asarray(image.psf, dtype=np.float64)
    if psf.ndim == 3:
        if "Y" not in image.channels:
            raise InputDataError(
                f"{image.path}: a reference PSF needs one channel or a Y channel, got "
                f"{', '.join(image.channels)}"
            )
        psf = psf[..., list(image.channels).index("Y")]
    total = float(np.sum(psf))
    if not (math.isfinite(total) and total > 0):
        raise InputDataError(f"{image.path}: the PSF's sum is {total:g}; expected light > 0")
    h, w = psf.shape
    if h == w:
        return psf
    half = min(h // 2, w // 2, (h - 1) - h // 2, (w - 1) - w // 2)
    cy, cx = h // 2, w // 2
    return psf[cy - half : cy + half + 1, cx - half : cx + half + 1]


def _image_bins(psf: np.ndarray, scale: float, lo: float, hi: float, n: int, path: Path):
    """The fit's annuli on the reference image's own pixels."""
    npix = psf.shape[0]
    reach = (npix // 2 - 1) * scale
    if reach < hi:
        raise InputDataError(
            f"{path}: the reference reaches {reach:.3g} deg from its centre, the fit needs "
            f"{hi:.3g} deg; narrow [range] theta_max_deg or give a larger image"
        )
    try:
        return RadialBins.build(npix, scale, lo, hi, n)
    except PhysicsRangeError as err:
        raise InputDataError(f"{path}: {err}") from None


def _check_covers(table: RadialTable, setup: CieFitSetup, path: Path) -> None:
    lo, hi = setup.theta_min_deg, setup.max_angle_deg()
    t0, t1 = float(table.theta_deg[0]), float(table.theta_deg[-1])
    if t0 > lo or t1 < hi:
        raise InputDataError(
            f"{path}: the reference covers {t0:.3g}-{t1:.3g} deg, the fit needs "
            f"{lo:g}-{hi:.3g} deg; narrow [range] (theta_min_deg, theta_max_deg) to the data"
        )
    inside = (table.theta_deg >= lo) & (table.theta_deg <= hi)
    if np.any(table.values[inside] <= 0):
        bad = float(table.theta_deg[inside][np.argmax(table.values[inside] <= 0)])
        raise InputDataError(
            f"{path}: the reference is 0 at {bad:.3g} deg inside the fitted range; a fit in "
            "log units needs light at every angle: narrow [range]"
        )


def _read_population(table: Any, i: int) -> Population:
    sec = Section(table, f"population[{i}]")
    region = sec.choice("region", REGIONS, "cornea")
    count_max = sec.get("count_max", int, required=True)
    values = {
        key: sec.get(key, float, required=True)
        for key in ("count_init", "radius_min_mm", "radius_max_mm", "radius_init_mm")
    }
    spread = sec.get("radius_spread", float, 0.3)
    region_radius = sec.get("region_radius_mm", float, 1.6)
    sec.finish()
    where = f"population[{i}]"
    if count_max < 1:
        raise ConfigError(f"{where}.count_max must be an integer >= 1, got {count_max}")
    if not 0 < values["count_init"] < count_max:
        raise ConfigError(
            f"{where}.count_init = {values['count_init']:g} must lie in (0, count_max = "
            f"{count_max})"
        )
    lo, init, hi = values["radius_min_mm"], values["radius_init_mm"], values["radius_max_mm"]
    if not 0 < lo < init < hi:
        raise ConfigError(
            f"{where}: expected 0 < radius_min_mm < radius_init_mm < radius_max_mm, got "
            f"{lo:g}, {init:g}, {hi:g}"
        )
    return Population(region, count_max, radius_spread=spread, region_radius_mm=region_radius,
                      **values)  # fmt: skip


def _read_setup(config: dict[str, Any], n_starts: int | None, max_steps: int | None):
    eye = Section(config.get("eye", {}), "eye")
    fields: dict[str, Any] = {}
    for key, kind in _EYE_KEYS.items():
        value = eye.get(key, kind, None)
        if value is not None:
            fields[key] = value
    wavelengths = eye.get("wavelengths_nm", list, None)
    eye.finish()
    if wavelengths is not None:
        try:
            fields["wavelengths_nm"] = tuple(float(w) for w in wavelengths)
        except (TypeError, ValueError):
            raise ConfigError(
                f"eye.wavelengths_nm must be a list of numbers, got {wavelengths!r}"
            ) from None
        if not fields["wavelengths_nm"]:
            raise ConfigError("eye.wavelengths_nm is empty; give at least one wavelength")
    tables = config.get("population")
    if tables is not None:
        if not isinstance(tables, list) or not tables:
            raise ConfigError("population must be one or more [[population]] tables")
        fields["populations"] = tuple(_read_population(t, i) for i, t in enumerate(tables))
    rng = Section(config.get("range", {}), "range")
    for key, kind in (("theta_min_deg", float), ("theta_max_deg", float), ("n_bins", int)):
        value = rng.get(key, kind, None)
        if value is not None:
            fields[key] = value
    rng.finish()
    solver = Section(config.get("solver", {}), "solver")
    # Read both keys even when overridden: a key the config gives is known either way.
    config_starts, config_steps = solver.get("n_starts", int, 3), solver.get("max_steps", int, 60)
    fields["n_starts"] = config_starts if n_starts is None else n_starts
    fields["max_steps"] = config_steps if max_steps is None else max_steps
    solver.finish()
    for key in ("n_starts", "max_steps", "aperture_npix", "npix"):
        if key in fields and fields[key] < 1:
            raise ConfigError(f"{key} must be an integer >= 1, got {fields[key]}")
    for key in ("pupil_diameter_mm", "pixel_scale_deg"):
        if key in fields and not (math.isfinite(fields[key]) and fields[key] > 0):
            raise ConfigError(f"eye.{key} must be a number > 0, got {fields[key]!r}")
    setup = CieFitSetup(**fields)
    setup.validate()
    return setup


def load_reference_fit(
    path: str | Path,
    *,
    out_dir: str | Path | None = None,
    n_starts: int | None = None,
    max_steps: int | None = None,
) -> ReferenceFit:
    """Read and check a reference-fit config (module docstring); nothing is fitted yet.

    **Raises:** `ConfigError` naming the key for unknown tables or keys, both or
    neither of ``cie`` and ``file``, bad eye or range values; `PhysicsRangeError` for an
    age outside 0-100 or a pigmentation outside 0-1.2, or a range the model's sampling
    does not cover; `InputDataError` for a reference file without a pixel scale, with
    non-increasing angles, or not covering the fitted range.
    """
    from invglare.reference.cie import cie_gsf

    config_path = Path(path)
    config = load_toml(config_path)
    check_sections(config, SECTIONS, str(config_path))
    base = config_path.parent

    name, folder = read_fit_section(config, config_path, out_dir)

    setup = _read_setup(config, n_starts, max_steps)

    rsec = Section(config["reference"], "reference")
    cie = rsec.get("cie", dict, None)
    file = rsec.get("file", str, None)
    rsec.finish()
    if (cie is None) == (file is None):
        raise ConfigError(
            f"{config_path}: [reference] needs exactly one of cie = {{ age = ..., "
            'pigmentation = ... }} and file = "..."'
        )
    if cie is not None:
        csec = Section(cie, "reference.cie")
        age = csec.get("age", float, required=True)
        pig = csec.get("pigmentation", float, required=True)
        csec.finish()
        cie_gsf(1.0, age, pig)  # the range checks, naming the value
        return ReferenceFit(name, folder, config_path, setup, cie=(float(age), float(pig)))

    ref_path = base / file
    loaded = load_reference_psf(ref_path)
    if isinstance(loaded, ReferenceImage):
        psf, scale = _square_psf(loaded), loaded.pixel_scale_deg
        # The annuli on the image's pixels: checks the coverage now, before any fitting.
        _image_bins(psf, scale, setup.theta_min_deg, setup.max_angle_deg(), setup.n_bins, ref_path)
        return ReferenceFit(
            name, folder, config_path, setup, reference_path=ref_path, image=psf,
            image_scale_deg=scale,
        )  # fmt: skip
    _check_covers(loaded, setup, ref_path)
    return ReferenceFit(name, folder, config_path, setup, reference=loaded, reference_path=ref_path)


__all__ = ["ReferenceFit", "is_reference_fit", "load_reference_fit"]
