"""Regression fitting: the eye model's radial glare spread function fitted to the CIE's.

The CIE general disability glare equation (:func:`invglare.reference.cie_gsf`)
summarises measured human straylight from 0.1° to 100°. invglare's eye
(:class:`~invglare.models.kakimoto.KakimotoGlare` of an
:class:`~invglare.aperture.eye.EyeAperture`) is a *diffraction* model: its PSF is
``|F[t_o P]|²`` of a rasterised pupil, so it describes light only up to the alias-free
angle of the raster, ``lambda / (2 · pitch)`` at the shortest wavelength — 1.1° for a
3 mm pupil on 256 samples at 460 nm, 2.2° on 512. Beyond that the model holds
nothing, and what the CIE puts there (fundus reflection, light through the eye wall,
the wide-angle tail of the cornea and lens) is not diffraction by anything the model
rasterises. So the fit covers
**0.1° to the model's largest alias-free angle** (a safety factor 0.9 below it, and
inside the output field), and the report says how much of the CIE's light lies beyond.
No smooth wide-angle term is added: such a term would fit the CIE by construction and
say nothing about the eye's structures.

**What is fitted.** The radially averaged GSF of the model (sr⁻¹: the PSF, energy per
pixel, over the pixel solid angle) in logarithmically spaced annuli, against the CIE
function averaged over the *same pixel centres* (both are point samples of a sr⁻¹
function, so the comparison is exact in its geometry). Residuals are
``log10(model) − log10(CIE)`` per annulus, so every decade of angle and of level counts
alike; they are minimised with Levenberg–Marquardt (optimistix) over the latent
parameters of an :class:`invglare.fit.ParameterSpace` (logit transforms keep every
value inside its bounds), from a few starts. The solver's Jacobian is a central
difference over ±0.1 latent units (±5-10 % of a count or radius), not the exact
derivative: the derivative with respect to a relaxed count is that of the one particle
fading in, whose interference with all the others (speckle) swamps the trend, and the
solver stalls where it starts (seen in practice; the profile's trend, which the finite
difference measures, is smooth).

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

**Limits, stated.** The CIE's steep inner terms (its first bracket, ``9.2e6 / …`` and
``1.5e5 / …``) describe the eye's optical blur and forward scatter near the core;
opaque particles can imitate them only by blocking a sizeable part of the pupil (about
half of its light in the bundled fits; the result reports the share), and the fitted
particle numbers are *effective* values of this model, not counts of real cells. The
residual wiggles by a few hundredths of a decade from annulus to annulus: the speckle of
one random draw of particles (fixed by `seed`).

**Example:**

```python
result = fit_cie(25.0, 0.5)                  # defaults: CieFitSetup()
print(result.summary())                     # parameters, residual in log10 units
write_cie_report([result], "reports")        # reports/cie/cie.md and figures
```
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import functools
import logging
import math
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from jaxtyping import Array, Float

from invglare.errors import ConfigError, PhysicsRangeError

__all__ = [
    "CieFitResult",
    "CieFitSetup",
    "Population",
    "RadialBins",
    "build_fit_model",
    "cie_target",
    "fit_cie",
    "fit_radial_gsf",
    "model_gsf",
    "parse_cie_spec",
    "write_cie_report",
]

log = logging.getLogger("invglare")

#: Step (latent units) of the finite-difference Jacobian of a fit (see `_prepare`).
FD_STEP = 0.1


# ------------------------------------------------------------------------------ setup


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


# ------------------------------------------------------------------------------ profiles


@dataclasses.dataclass(frozen=True, eq=False)
class RadialBins:
    """Logarithmic annuli on the output grid: which pixel goes where (static, numpy).

    **Fields:** `index` (per pixel, the annulus or `n_bins` for none), `counts`
    (pixels per annulus), `theta_deg` (mean pixel-centre angle per annulus), `edges_deg`,
    `pixel_theta_deg` (every pixel centre's angle), `pixel_scale_deg`.
    """

    index: np.ndarray
    counts: np.ndarray
    theta_deg: np.ndarray
    edges_deg: np.ndarray
    pixel_theta_deg: np.ndarray
    pixel_scale_deg: float

    @classmethod
    def build(cls, npix: int, pixel_scale_deg: float, lo_deg: float, hi_deg: float, n: int):
        c = npix // 2
        yy, xx = np.mgrid[:npix, :npix] - c
        theta = np.hypot(xx, yy) * pixel_scale_deg
        edges = np.geomspace(lo_deg, hi_deg, n + 1)
        idx = np.searchsorted(edges, theta, side="right") - 1
        idx = np.where((theta >= lo_deg) & (theta < hi_deg), idx, n)
        counts = np.bincount(idx.ravel(), minlength=n + 1)[:n]
        if np.any(counts == 0):
            empty = int(np.argmax(counts == 0))
            raise PhysicsRangeError(
                f"annulus {empty} ({edges[empty]:.3g}-{edges[empty + 1]:.3g} deg) holds no "
                f"pixel centre at {pixel_scale_deg:g} deg/px; use fewer bins or finer pixels"
            )
        sums = np.bincount(idx.ravel(), weights=theta.ravel(), minlength=n + 1)[:n]
        return cls(idx.ravel(), counts, sums / counts, edges, theta, float(pixel_scale_deg))

    @property
    def n_bins(self) -> int:
        return int(self.counts.size)

    def mean(self, image) -> Any:
        """Mean of a ``(npix, npix)`` image per annulus (jax.numpy, differentiable)."""
        import jax.numpy as jnp

        flat = jnp.reshape(image, (-1,))
        sums = jnp.zeros(self.n_bins + 1, flat.dtype).at[self.index].add(flat)[: self.n_bins]
        return sums / jnp.asarray(self.counts, flat.dtype)


def photopic_psf(model) -> Float[Array, "npix npix"]:
    """The luminance (photopic, V(λ)-weighted) PSF of a Kakimoto model, unit energy.

    One field, propagated at each wavelength, summed with the Y weights of the model's
    spectrum (normalised to 1): the Y of its RGB PSF, without the RGB round trip.
    """
    import jax
    import jax.numpy as jnp

    field = model.field()
    lams = model.spectrum.wavelengths_nm
    psfs = jax.vmap(lambda lam: model.propagator(field, lam))(lams)
    wy = model.spectrum.weights_xyz[:, 1]
    return jnp.tensordot(wy / jnp.sum(wy), psfs, axes=1)


def model_gsf(model, bins: RadialBins) -> Float[Array, " n_bins"]:
    """The model's photopic GSF (sr⁻¹) per annulus: PSF over pixel solid angle, averaged."""
    omega = math.radians(bins.pixel_scale_deg) ** 2
    return bins.mean(photopic_psf(model)) / omega


def annulus_mean(gsf: Callable[[Any], Any], bins: RadialBins) -> np.ndarray:
    """A radial function (of angle in degrees) averaged over each annulus's pixel centres,
    the way :func:`model_gsf` averages the model: both are point samples of one function."""
    import jax

    with jax.enable_x64(True):
        inside = bins.index < bins.n_bins
        values = np.zeros(bins.index.size)
        values[inside] = np.asarray(gsf(bins.pixel_theta_deg.ravel()[inside]))
    sums = np.bincount(bins.index, weights=values, minlength=bins.n_bins + 1)[: bins.n_bins]
    return sums / bins.counts


def cie_target(age: float, pigmentation: float, bins: RadialBins) -> np.ndarray:
    """The CIE GSF (sr⁻¹) averaged over each annulus's pixel centres, like :func:`model_gsf`."""
    from invglare.reference.cie import cie_gsf

    # Validate age and pigmentation on scalars first: errors then name the value.
    cie_gsf(1.0, age, pigmentation)
    return annulus_mean(lambda t: cie_gsf(t, age, pigmentation), bins)


# ------------------------------------------------------------------------------ fitting


@dataclasses.dataclass(eq=False)
class CieFitResult:
    """A fit of the eye's radial GSF to a target (the CIE function or a synthetic one).

    **Fields:** `label`; `age`, `pigmentation` (``None`` for a non-CIE target);
    `values` (``{path: value}``); `theta_deg`, `target_gsf`, `model_gsf` (per annulus);
    `residual_log10` (``log10(model / target)`` per annulus); `rms_log10`, `max_log10`;
    `loss`; `converged`; `n_steps`; `starts` (final loss of every start); `seconds`;
    `setup`; `initial_gsf` (the first start's GSF); `blocked_fraction` (of the pupil's
    light, stopped by the fitted particles: ``1 − Σ P² / Σ opening²``); `energy_beyond`
    (fraction of the CIE's light beyond the fitted range within 100°, or ``None``).
    """

    label: str
    age: float | None
    pigmentation: float | None
    values: dict[str, float]
    theta_deg: np.ndarray
    target_gsf: np.ndarray
    model_gsf: np.ndarray
    residual_log10: np.ndarray
    rms_log10: float
    max_log10: float
    loss: float
    converged: bool
    n_steps: int
    starts: list[float]
    seconds: float
    setup: CieFitSetup
    initial_gsf: np.ndarray
    blocked_fraction: float = math.nan
    energy_beyond: float | None = None

    def summary(self) -> str:
        lines = [
            f"{self.label}: rms {self.rms_log10:.3f}, max {self.max_log10:.3f} log10 units "
            f"over {self.theta_deg[0]:.3g}-{self.theta_deg[-1]:.3g} deg "
            f"(solver {'converged' if self.converged else 'stopped at max_steps'}, "
            f"{self.n_steps} steps, {self.seconds:.0f} s); the particles block "
            f"{100 * self.blocked_fraction:.0f} % of the pupil's light"
        ]
        lines += [f"  {path} = {value:.5g}" for path, value in self.values.items()]
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        return {
            "label": self.label,
            "age": self.age,
            "pigmentation": self.pigmentation,
            "values": self.values,
            "theta_deg": self.theta_deg.tolist(),
            "target_gsf_sr": self.target_gsf.tolist(),
            "model_gsf_sr": self.model_gsf.tolist(),
            "residual_log10": self.residual_log10.tolist(),
            "rms_log10": self.rms_log10,
            "max_log10": self.max_log10,
            "loss": self.loss,
            "converged": self.converged,
            "n_steps": self.n_steps,
            "start_losses": self.starts,
            "seconds": self.seconds,
            "blocked_fraction": self.blocked_fraction,
            "energy_beyond_fit_range": self.energy_beyond,
            "setup": dataclasses.asdict(self.setup),
        }


@dataclasses.dataclass(frozen=True, eq=False)
class _Prepared:
    """What every fit with one setup shares: model, space, annuli and compiled functions."""

    model: Any
    space: Any
    bins: RadialBins
    solve: Callable
    residuals: Callable


@functools.lru_cache(maxsize=4)
def _prepare(setup: CieFitSetup) -> _Prepared:
    """Build (once per setup and process) the model and the jitted solver.

    Cached so that fits for several ages, or a recovery and a CIE fit, compile once:
    the target is an argument of the compiled functions, not a constant in them.
    Call inside ``jax.enable_x64(True)``.
    """
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import optimistix as optx

    model, space = build_fit_model(setup)
    bins = RadialBins.build(
        setup.npix, setup.pixel_scale_deg, setup.theta_min_deg, setup.max_angle_deg(),
        setup.n_bins,
    )  # fmt: skip

    def exact(latent, model, log_target):
        fitted = space.apply(model, space.from_latent(latent))
        gsf = model_gsf(fitted, bins)
        # A floor far below any GSF the model makes keeps log() finite if a bin empties.
        return jnp.log10(jnp.maximum(gsf, 1e-12)) - log_target

    # The exact derivative with respect to a relaxed count is the effect of the one
    # particle fading in, and its interference with all the others (speckle) swamps the
    # trend: the solver then stalls where it starts. So the Jacobian is a central
    # difference over +-FD_STEP latent units (about +-5-10 % of a count or a radius),
    # the slope of the profile's trend, which is what a fit of a statistic needs.
    @jax.custom_jvp
    def smoothed(latent, model, log_target):
        return exact(latent, model, log_target)

    @smoothed.defjvp
    def _smoothed_jvp(primals, tangents):
        latent, model, log_target = primals
        d_latent = tangents[0]  # the model and the target are data: their tangents are 0
        steps = FD_STEP * jnp.eye(latent.shape[0], dtype=latent.dtype)
        probes = jnp.concatenate([latent + steps, latent - steps])
        values = jax.vmap(lambda y: exact(y, model, log_target))(probes)
        n = latent.shape[0]
        jac = (values[:n] - values[n:]).T / (2.0 * FD_STEP)  # (n_bins, p)
        return exact(latent, model, log_target), jac @ d_latent

    def residuals(latent, args):
        model, log_target = args
        return smoothed(latent, model, log_target)

    # Tolerances on the latent step and the loss: 1e-4 is far below what matters in
    # log10 units (0.01 is a 2 % change of the GSF).
    solver = optx.LevenbergMarquardt(rtol=1e-4, atol=1e-6)

    @eqx.filter_jit
    def solve(y0, args):
        sol = optx.least_squares(
            residuals, solver, y0, args=args, max_steps=setup.max_steps, throw=False
        )
        return sol.value, sol.result == optx.RESULTS.successful, sol.stats["num_steps"]

    return _Prepared(model, space, bins, solve, eqx.filter_jit(residuals))


def fit_radial_gsf(
    target_gsf: Float[np.ndarray, " n_bins"] | Callable[[RadialBins], np.ndarray],
    setup: CieFitSetup | None = None,
    *,
    label: str = "fit",
    starts: Sequence[dict[str, float]] | None = None,
    progress: bool | None = None,
) -> CieFitResult:
    """Fit the eye model's radial GSF to a target GSF over the setup's annuli.

    **Arguments:**

    - `target_gsf`: sr⁻¹ per annulus (of :meth:`RadialBins.build` for this setup), or
      a function of the :class:`RadialBins` returning it.
    - `setup`: a :class:`CieFitSetup` (default: the defaults).
    - `label`: a name for reports.
    - `starts`: physical start values ``{path: value}``; default: the populations'
      initial values, then ``setup.n_starts - 1`` Latin-hypercube starts.
    - `progress`: a tqdm bar over the starts (``None``: on a terminal only).

    Runs in float64. **Returns:** a :class:`CieFitResult` of the best start.

    **Raises:** `PhysicsRangeError` / `ConfigError` for a bad setup; `ConfigError` for
    a target of the wrong length or with values that are not finite and > 0.
    """
    import jax
    import jax.numpy as jnp
    from tqdm import tqdm

    setup = CieFitSetup() if setup is None else setup
    setup.validate()
    t0 = time.perf_counter()
    with jax.enable_x64(True):
        prep = _prepare(setup)
        space, bins = prep.space, prep.bins
        target = np.asarray(target_gsf(bins) if callable(target_gsf) else target_gsf, float)
        if target.shape != (bins.n_bins,):
            raise ConfigError(
                f"the target GSF has shape {target.shape}; expected ({bins.n_bins},), one value "
                "per annulus of the setup"
            )
        if not np.all(np.isfinite(target) & (target > 0)):
            bad = int(np.argmax(~(np.isfinite(target) & (target > 0))))
            raise ConfigError(
                f"target GSF value {target[bad]!r} at {bins.theta_deg[bad]:.3g} deg; expected "
                "finite values > 0 (sr^-1)"
            )
        args = (prep.model, jnp.log10(jnp.asarray(target)))
        if starts is None:
            latents = [space.initial_latent()]
            if setup.n_starts > 1:
                extra = space.sample_starts(jax.random.key(setup.seed + 1), setup.n_starts - 1)
                latents += list(extra)
        else:
            latents = [space.to_latent(space.values_from(s)) for s in starts]
        r0 = np.asarray(prep.residuals(jnp.asarray(latents[0]), args))
        initial = target * 10.0**r0
        best = None
        losses = []
        disable = None if progress is None else not progress
        for y0 in tqdm(latents, desc=f"fit {label}", unit="start", disable=disable):
            value, ok, steps = prep.solve(jnp.asarray(y0), args)
            r = np.asarray(prep.residuals(value, args))
            loss = float(np.sum(r * r))
            losses.append(loss if math.isfinite(loss) else math.inf)
            if best is None or losses[-1] < best[0]:
                best = (losses[-1], value, bool(ok), int(steps), r)
        loss, value, ok, steps, r = best
        values = space.as_dict(space.from_latent(value))
        fitted = space.apply(prep.model, space.from_latent(value))
        grid = fitted.propagator.grid
        kept = jnp.sum(fitted.aperture.pupil_transmission(grid) ** 2)
        blocked = 1.0 - float(kept / jnp.sum(fitted.aperture.pupil.coverage(grid) ** 2))
    return CieFitResult(
        label=label,
        age=None,
        pigmentation=None,
        values=values,
        theta_deg=bins.theta_deg,
        target_gsf=target,
        model_gsf=target * 10.0**r,
        residual_log10=r,
        rms_log10=float(np.sqrt(np.mean(r * r))),
        max_log10=float(np.max(np.abs(r))),
        loss=loss,
        converged=ok,
        n_steps=steps,
        starts=losses,
        seconds=time.perf_counter() - t0,
        setup=setup,
        initial_gsf=initial,
        blocked_fraction=blocked,
    )


def _energy_beyond(age: float, pigmentation: float, theta_deg: float) -> float:
    """Fraction of the CIE GSF's light between `theta_deg` and 100°, of all within 100°."""
    import jax
    from scipy.integrate import quad

    from invglare.reference.cie import cie_gsf

    def ring(t_deg: float) -> float:
        # dOmega = 2 pi theta dtheta (small-angle form, as the GSF's normalisation uses).
        value = float(cie_gsf(t_deg, age, pigmentation, extrapolate=True))
        return value * 2.0 * math.pi * math.radians(t_deg) * math.radians(1.0)

    with jax.enable_x64(True):
        inner = quad(ring, 0.0, theta_deg, points=[0.01, 0.1], limit=200)[0]
        outer = quad(ring, theta_deg, 100.0, points=[1.0, 10.0], limit=200)[0]
    return outer / (inner + outer)


def fit_cie(
    age: float,
    pigmentation: float,
    setup: CieFitSetup | None = None,
    *,
    progress: bool | None = None,
) -> CieFitResult:
    """Fit the eye model to the CIE GSF for an age (years) and pigmentation factor.

    **Raises:** `PhysicsRangeError` naming an age outside 0-100 or a pigmentation
    outside 0-1.2 (from :func:`~invglare.reference.cie_gsf`), before any model is built.

    **Example:**

    ```python
    res = fit_cie(70.0, 1.0)
    res.rms_log10      # residual across the fitted range, log10 units
    ```
    """
    from invglare.reference.cie import cie_gsf

    cie_gsf(1.0, age, pigmentation)  # range checks with the offending value in the message
    setup = CieFitSetup() if setup is None else setup
    label = f"CIE age {age:g}, pigmentation {pigmentation:g}"
    result = fit_radial_gsf(
        lambda bins: cie_target(age, pigmentation, bins), setup, label=label, progress=progress
    )
    result.age = float(age)
    result.pigmentation = float(pigmentation)
    result.energy_beyond = _energy_beyond(age, pigmentation, float(result.setup.max_angle_deg()))
    return result


def parse_cie_spec(spec: str) -> tuple[float, float]:
    """``"AGE,PIGMENT"`` → ``(age, pigmentation)``, e.g. ``"25,0.5"``.

    **Raises:** `ConfigError` for anything but two numbers; `PhysicsRangeError` for
    values outside 0-100 years or 0-1.2.
    """
    from invglare.reference.cie import cie_gsf

    parts = [p.strip() for p in str(spec).split(",")]
    try:
        if len(parts) != 2:
            raise ValueError
        age, pig = float(parts[0]), float(parts[1])
    except ValueError:
        raise ConfigError(
            f"--cie {spec!r}: expected AGE,PIGMENT, two numbers such as 25,0.5 "
            "(age in years, pigmentation 0 dark to 1.2 very light eyes)"
        ) from None
    cie_gsf(1.0, age, pig)
    return age, pig


# ------------------------------------------------------------------------------ reporting


def _slug(result: CieFitResult) -> str:
    return f"cie_A{result.age:g}_p{result.pigmentation:g}".replace(".", "_")


def _short(path: str) -> str:
    return (
        path.replace("aperture.particles[0]", "cornea")
        .replace("aperture.particles[1]", "lens")
        .replace(".radius_mean_mm", " radius (mm)")
        .replace(".count", " count")
    )


def _figure(results: Sequence[CieFitResult], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import jax
    import matplotlib.pyplot as plt

    from invglare.files.atomic import atomic_path
    from invglare.reference.cie import cie_gsf

    fig, (ax, axr) = plt.subplots(
        2, 1, figsize=(7, 7), sharex=True, gridspec_kw={"height_ratios": [3, 1]},
        constrained_layout=True,
    )  # fmt: skip
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    wide = np.geomspace(0.1, 100.0, 300)
    for k, res in enumerate(results):
        c = colours[k % len(colours)]
        if res.age is None:  # a reference that is not the CIE's: its annulus means
            name = res.label
            ax.loglog(res.theta_deg, res.target_gsf, "s", color=c, ms=4, mfc="none",
                      label=f"reference {name}")  # fmt: skip
        else:
            with jax.enable_x64(True):
                curve = np.asarray(cie_gsf(wide, res.age, res.pigmentation))
            name = f"A={res.age:g}, p={res.pigmentation:g}"
            ax.loglog(wide, curve, color=c, lw=1, alpha=0.5, label=f"CIE {name}")
        ax.loglog(res.theta_deg, res.model_gsf, "o-", color=c, ms=3, label=f"eye model {name}")
        axr.semilogx(res.theta_deg, res.residual_log10, "o-", color=c, ms=3)
    lo, hi = results[0].theta_deg[0], results[0].theta_deg[-1]
    for a in (ax, axr):
        a.axvspan(lo, hi, color="0.9", zorder=0)
    ax.set_ylabel("GSF (sr$^{-1}$)")
    ax.set_title(title)
    ax.legend(fontsize=7)
    axr.axhline(0.0, color="0.3", lw=0.8)
    cie = all(r.age is not None for r in results)
    axr.set_ylabel("log10(model / CIE)" if cie else "log10(model / reference)")
    axr.set_xlabel("angle from the source (deg)")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)


def write_cie_report(
    results: Sequence[CieFitResult], out_dir: str | os.PathLike[str] = "reports"
) -> Path:
    """Write ``<out_dir>/cie/cie.md``, a log-log figure per fit, one of all, and ``fits.json``.

    **Returns:** the markdown path. Files are written atomically.
    """
    from invglare.files.atomic import write_json_atomic, write_text_atomic

    if not results or any(r.age is None for r in results):
        raise ConfigError("write_cie_report needs CIE fits (from fit_cie)")
    folder = Path(out_dir) / "cie"
    for r in results:
        _figure([r], folder / f"{_slug(r)}.png", r.label)
    if len(results) > 1:
        _figure(results, folder / "cie_all.png", "eye model vs CIE glare spread function")
    setup = results[0].setup
    stamp = dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    paths = list(results[0].values)
    lines = [
        "# The eye model fitted to the CIE glare spread function",
        "",
        f"`invglare regress --cie`, {stamp}. Model: a {setup.pupil_diameter_mm:g} mm pupil at "
        f"{min(setup.wavelengths_nm):g}-{max(setup.wavelengths_nm):g} nm "
        f"({len(setup.wavelengths_nm)} wavelengths, V(λ)-weighted) with "
        f"{len(setup.populations)} particle populations "
        f"({', '.join(p.region for p in setup.populations)}), {setup.aperture_npix} pupil "
        f"samples, {setup.npix}² output pixels of {setup.pixel_scale_deg:g}° (MFT). Fitted "
        f"range {setup.theta_min_deg:g}°–{setup.max_angle_deg():.3g}° in {setup.n_bins} "
        f"logarithmic annuli: the model's raster is alias-free to "
        f"{setup.alias_free_deg():.3g}° and the fit stops at 0.9 of that. Residuals are "
        "`log10(model / CIE)` per annulus; Levenberg–Marquardt from "
        f"{setup.n_starts} start(s).",
        "",
        "| age | p | rms log10 | max log10 | CIE light beyond the range | "
        + " | ".join(_short(p) for p in paths)
        + " | pupil light blocked | converged | time s |",
        "|---|---|---|---|---|" + "---|" * len(paths) + "---|---|---|",
    ]
    for r in results:
        beyond = "–" if r.energy_beyond is None else f"{100 * r.energy_beyond:.1f} %"
        vals = " | ".join(f"{r.values[p]:.4g}" for p in paths)
        lines.append(
            f"| {r.age:g} | {r.pigmentation:g} | {r.rms_log10:.3f} | {r.max_log10:.3f} | "
            f"{beyond} | {vals} | {100 * r.blocked_fraction:.0f} % | "
            f"{'yes' if r.converged else 'no'} | {r.seconds:.0f} |"
        )
    lines += [""]
    for r in results:
        lines.append(f"![{r.label}](cie/{_slug(r)}.png)".replace("cie/cie/", "cie/"))
    if len(results) > 1:
        lines += ["", "![all fits](cie_all.png)"]
        moved = _what_moved(results, paths)
        if moved:
            lines += ["", "## What moved", "", moved]
    lines += [
        "",
        "## Reading it",
        "",
        "A residual of 0.1 log10 units is a factor 1.26. The CIE light beyond the range is the",
        "share of its glare within 100° that lies outside what the model's sampling covers; the",
        "fit says nothing about it. The residuals wiggle by a few hundredths from annulus to",
        "annulus: that is the speckle of one random draw of particles, not noise in the CIE.",
        "The particle counts and radii are effective values of this diffraction model (opaque",
        "particles in one plane), not counts of cells; the share of the pupil's light they",
        "block shows what it takes opaque obstacles to reach the CIE's level near 0.1°, where",
        "the CIE's terms stand for the eye's optical blur rather than for scattering. See",
        "`invglare/reference/cie_fit.py` for the reasoning and the limits.",
        "",
    ]
    # Figures sit next to the markdown, so links are relative to the cie/ folder.
    text = "\n".join(lines).replace("](cie/", "](")
    write_json_atomic(folder / "fits.json", [r.to_dict() for r in results])
    path = folder / "cie.md"
    write_text_atomic(path, text)
    return path


def write_gsf_report(
    result: CieFitResult,
    folder: str | os.PathLike[str],
    *,
    reference: str,
    config_path: str | os.PathLike[str] | None = None,
) -> Path:
    """Write one reference fit's report folder: ``report.md``, ``gsf.png``, ``fit.json``.

    The folder is replaced as a whole once complete (an interrupted run leaves the
    previous report). `reference` says in words what was fitted (the CIE's age and
    pigmentation, or the file). **Returns:** the folder.
    """
    from invglare.files.atomic import dumps_json
    from invglare.fit.report import atomic_directory

    setup = result.setup
    beyond = (
        ""
        if result.energy_beyond is None
        else f" The CIE puts {100 * result.energy_beyond:.1f} % of its light within 100° "
        "beyond the fitted range, which this fit says nothing about."
    )
    lines = [
        f"# Reference fit: {result.label}",
        "",
        f"- **Reference:** {reference}",
        f"- **Config:** `{config_path}`" if config_path else None,
        f"- **Model:** a {setup.pupil_diameter_mm:g} mm pupil at {min(setup.wavelengths_nm):g}-"
        f"{max(setup.wavelengths_nm):g} nm ({len(setup.wavelengths_nm)} wavelengths, "
        f"V(λ)-weighted), particle populations {', '.join(p.region for p in setup.populations)}"
        f", {setup.aperture_npix} pupil samples, {setup.npix}² output pixels of "
        f"{setup.pixel_scale_deg:g}° (MFT), seed {setup.seed}",
        f"- **Fitted:** the radially averaged GSF in {setup.n_bins} logarithmic annuli over "
        f"{setup.theta_min_deg:g}°–{setup.max_angle_deg():.3g}° (the raster is alias-free to "
        f"{setup.alias_free_deg():.3g}°), residuals `log10(model / reference)`; "
        f"Levenberg–Marquardt from {len(result.starts)} start(s)",
        "",
        "## Result",
        "",
        f"Residual **{result.rms_log10:.3f}** log10 units rms, {result.max_log10:.3f} at worst "
        f"(a factor {10**result.rms_log10:.3f} and {10**result.max_log10:.3f}); "
        f"{'converged' if result.converged else 'stopped at max_steps'} after "
        f"{result.n_steps} steps; {result.seconds:.0f} s. The fitted particles block "
        f"{100 * result.blocked_fraction:.0f} % of the pupil's light.{beyond}",
        "",
        "| parameter | value |",
        "|---|---:|",
        *(f"| `{p}` ({_short(p)}) | {v:.5g} |" for p, v in result.values.items()),
        "",
        "| angle (deg) | reference (sr⁻¹) | model (sr⁻¹) | log10(model / reference) |",
        "|---:|---:|---:|---:|",
        *(
            f"| {t:.3g} | {a:.4g} | {m:.4g} | {r:+.3f} |"
            for t, a, m, r in zip(
                result.theta_deg,
                result.target_gsf,
                result.model_gsf,
                result.residual_log10,
                strict=True,
            )
        ),
        "",
        "![GSF](gsf.png)",
        "",
        "The particle counts and radii are effective values of this diffraction model (opaque",
        "particles in one plane), not counts of cells; see `invglare/reference/cie_fit.py`.",
        "",
    ]
    with atomic_directory(folder) as tmp:
        _figure([result], tmp / "gsf.png", result.label)
        (tmp / "report.md").write_text("\n".join(x for x in lines if x is not None), "utf-8")
        (tmp / "fit.json").write_text(dumps_json(result.to_dict()), "utf-8")
    return Path(folder)


def _what_moved(results: Sequence[CieFitResult], paths: list[str]) -> str:
    """One sentence per pigmentation: how each parameter changed from the youngest age."""
    sentences = []
    for pig in sorted({r.pigmentation for r in results}):
        group = sorted((r for r in results if r.pigmentation == pig), key=lambda r: r.age)
        if len(group) < 2:
            continue
        ages = " → ".join(f"{r.age:g}" for r in group)
        parts = []
        for p in paths:
            trail = " → ".join(f"{r.values[p]:.3g}" for r in group)
            ratio = group[-1].values[p] / group[0].values[p] if group[0].values[p] else math.inf
            parts.append(f"{_short(p)} {trail} (×{ratio:.2f})")
        sentences.append(f"With age ({ages}, p = {pig:g}): " + "; ".join(parts) + ".")
    for age in sorted({r.age for r in results}):
        group = sorted((r for r in results if r.age == age), key=lambda r: r.pigmentation)
        if len(group) < 2:
            continue
        pigs = " → ".join(f"{r.pigmentation:g}" for r in group)
        parts = [f"{_short(p)} " + " → ".join(f"{r.values[p]:.3g}" for r in group) for p in paths]
        sentences.append(f"With pigmentation ({pigs}, age {age:g}): " + "; ".join(parts) + ".")
    return "\n\n".join(sentences)
