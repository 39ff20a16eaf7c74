"""The eye of the CIE fitting study and its free parameters.

**The eye.** A round pupil (3 mm: a photopic pupil, as in the glare measurements the
CIE equation summarises) in equal-energy light at 460-640 nm, the seven monochromatic
PSFs summed with the photopic weights V(λ) (the CIE's function is photopic; the
wavelengths also average out part of the speckle), no lids or lashes (they add
streaks along fixed directions, which an azimuthal average of a population of eyes
does not have), and two populations of opaque particles, the scatterers of the model:

- ``cornea``: many small particles (radius 2-20 µm) spread over the pupil;
- ``lens_nucleus``: fewer, larger ones (10-100 µm) concentrated towards the axis.

Their counts and mean radii are the four free parameters (log-normal radii with a
fixed spread). A particle of radius ``a`` scatters a flat halo out to
``~lambda / (4 a)`` and ``theta⁻³`` beyond, and the count sets its level, so the small
population shapes the wide angles and the large one the steep part near 0.1°.

**Example:**

```python
setup = CieFitSetup(aperture_npix=512)   # a finer pupil raster reaches wider angles
setup.max_angle_deg()                    # the largest fitted angle (deg)
model, space = build_fit_model(setup)
```
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

from invglare.errors import ConfigError, PhysicsRangeError

__all__ = [
    "DEFAULT_POPULATIONS",
    "CieFitSetup",
    "Population",
    "build_fit_model",
    "eye_config",
    "parameter_space",
]


@dataclasses.dataclass(frozen=True)
class Population:
    """One population of particles whose count and mean radius are fitted.

    **Fields:** `region` (``"cornea"``, ``"lens_nucleus"`` or ``"vitreous"``);
    `count_max` (the pool size `n_max`, and the count's upper bound); `count_init`;
    `radius_min_mm`, `radius_max_mm`, `radius_init_mm` (bounds and start of the mean
    radius); `radius_spread` (fixed log-normal sigma); `region_radius_mm`.
    """

    region: str
    count_max: int
    count_init: float
    radius_min_mm: float
    radius_max_mm: float
    radius_init_mm: float
    radius_spread: float = 0.3
    region_radius_mm: float = 1.6


#: The two populations of the default fit (module docstring).
DEFAULT_POPULATIONS = (
    # Initial counts are not integers: a relaxed count has no gradient at an integer.
    Population("cornea", 3000, 800.5, 0.002, 0.02, 0.006, region_radius_mm=1.6),
    Population("lens_nucleus", 400, 60.5, 0.01, 0.1, 0.03, region_radius_mm=2.0),
)


@dataclasses.dataclass(frozen=True)
class CieFitSetup:
    """Model and sampling of a CIE fit (defaults: the module docstring's eye).

    **Fields:**

    - `pupil_diameter_mm`: the eye's fixed pupil.
    - `wavelengths_nm`: the light (equal energy), combined with the photopic weights
      V(λ) (the Y of CIE 1931) into one luminance PSF.
    - `populations`: the fitted particle populations.
    - `aperture_npix`: pupil raster size; it sets the largest alias-free angle.
    - `npix`, `pixel_scale_deg`: the output grid (matrix Fourier transform).
    - `theta_min_deg`, `theta_max_deg`: the fitted range; `theta_max_deg` ``None``
      takes the largest the sampling supports (:meth:`max_angle_deg`).
    - `n_bins`: logarithmic annuli across the range.
    - `seed`: the particles' random draws (fixed for the whole fit: common random
      numbers, so the objective is deterministic).
    - `n_starts`: starts of the fit (the first is the populations' initial values,
      the others spread across the bounds).
    - `max_steps`: Levenberg–Marquardt steps per start.
    - `draws`: 0, or how many eyes with the fitted parameters (particles drawn anew) are
      simulated to measure the scatter of the GSF between eyes: the fit is then repeated
      with each annulus weighted by it, and the result carries standard errors that
      include it (a target is one eye, the model's draw another).
    """

    pupil_diameter_mm: float = 3.0
    wavelengths_nm: tuple[float, ...] = (460.0, 490.0, 520.0, 550.0, 580.0, 610.0, 640.0)
    populations: tuple[Population, ...] = DEFAULT_POPULATIONS
    aperture_npix: int = 256
    npix: int = 108
    pixel_scale_deg: float = 0.02
    theta_min_deg: float = 0.1
    theta_max_deg: float | None = None
    n_bins: int = 20
    seed: int = 0
    n_starts: int = 3
    max_steps: int = 60
    draws: int = 0

    def pitch_mm(self) -> float:
        """The pupil raster's pitch (the model's default window: the pupil plus 2 px a side)."""
        return self.pupil_diameter_mm / (self.aperture_npix - 4)

    def alias_free_deg(self) -> float:
        """``lambda / (2 · pitch)`` in degrees at the shortest wavelength: beyond, it aliases."""
        return math.degrees(min(self.wavelengths_nm) * 1e-6 / (2.0 * self.pitch_mm()))

    def max_angle_deg(self) -> float:
        """The largest fitted angle: 0.9 of the alias-free angle, inside the output field."""
        half_field = (self.npix // 2 - 1) * self.pixel_scale_deg
        limit = min(0.9 * self.alias_free_deg(), half_field)
        return limit if self.theta_max_deg is None else float(self.theta_max_deg)

    def validate(self) -> None:
        """Raise `PhysicsRangeError` / `ConfigError` naming a bad value."""
        if not self.populations:
            raise ConfigError("a CIE fit needs at least one particle population")
        if not 0 < self.theta_min_deg < self.max_angle_deg():
            raise PhysicsRangeError(
                f"theta_min_deg = {self.theta_min_deg:g} must lie in (0, {self.max_angle_deg():g})"
                " deg, the largest angle the model's sampling covers"
            )
        if self.theta_max_deg is not None and self.theta_max_deg > 0.9 * self.alias_free_deg():
            raise PhysicsRangeError(
                f"theta_max_deg = {self.theta_max_deg:g} deg is beyond 0.9 x the alias-free "
                f"angle {self.alias_free_deg():.3g} deg of a {self.aperture_npix}-sample pupil; "
                "raise aperture_npix or lower theta_max_deg"
            )
        if self.theta_min_deg < self.pixel_scale_deg * 3:
            raise PhysicsRangeError(
                f"theta_min_deg = {self.theta_min_deg:g} deg is less than 3 pixels "
                f"({self.pixel_scale_deg:g} deg/px): the innermost annulus would hold too few "
                "pixels to average the speckle"
            )
        if self.n_bins < 4:
            raise ConfigError(f"n_bins must be >= 4, got {self.n_bins}")
        if self.draws and (int(self.draws) != self.draws or self.draws < 8):
            raise ConfigError(f"draws must be 0 or an integer >= 8, got {self.draws!r}")


def eye_config(setup: CieFitSetup) -> dict[str, Any]:
    """The model config (as for :func:`~invglare.config.model.build_model`) of the fit's eye.

    Counts and radii are at their *upper* bounds: the particles' stamp windows are
    sized when the model is built, and must hold the largest particle the fit may reach.
    """
    particles = [
        {
            "region": pop.region,
            "count": float(pop.count_max),
            "n_max": int(pop.count_max),
            "radius_mean_mm": float(pop.radius_max_mm),
            "radius_spread": float(pop.radius_spread),
            "region_radius_mm": float(pop.region_radius_mm),
        }
        for pop in setup.populations
    ]
    return {
        "model": {
            "kind": "eye",
            "focal_length_mm": 17.0,
            "masking": "fixed",
            "colour": "spectral",
            "aperture_npix": int(setup.aperture_npix),
            "method": "mft",
            "eye": {
                "seed": int(setup.seed),
                "pupil": {"diameter_mm": float(setup.pupil_diameter_mm)},
                "particles": particles,
            },
        },
        "output": {"npix": int(setup.npix), "pixel_scale_deg": float(setup.pixel_scale_deg)},
        "spectrum": {"wavelengths_nm": [float(w) for w in setup.wavelengths_nm]},
    }


def parameter_space(setup: CieFitSetup):
    """The free parameters: count and mean radius of each population (logit transforms)."""
    from invglare.fit import Parameter, ParameterSpace

    params = []
    for i, pop in enumerate(setup.populations):
        base = f"aperture.particles[{i}]"
        params.append(Parameter(f"{base}.count", 0.0, float(pop.count_max), pop.count_init))
        params.append(
            Parameter(
                f"{base}.radius_mean_mm", pop.radius_min_mm, pop.radius_max_mm, pop.radius_init_mm
            )
        )
    return ParameterSpace(params)


def build_fit_model(setup: CieFitSetup):
    """The eye model of the fit, with stamp windows sized for the upper bounds.

    **Returns:** ``(model, space)``: the model (parameters at the upper bounds; apply
    values with ``space.apply``) and its :func:`parameter_space`.
    """
    import equinox as eqx

    from invglare.config.model import build_model

    setup.validate()
    model = build_model(eye_config(setup), source="CIE fit eye")
    # Windows exactly as large as the largest particle the bounds allow (no extra headroom).
    grid = model.propagator.grid
    aperture = model.aperture.with_stamp_windows(grid, headroom=1.0)
    model = eqx.tree_at(lambda m: m.aperture, model, aperture)
    space = parameter_space(setup)
    space.check(model)
    return model, space
