"""The fit of the CIE study: the eye model's radial glare spread function fitted to a reference.

The CIE general disability glare equation (:func:`invglare.reference.cie_gsf`)
summarises measured human straylight from 0.1° to 100°. invglare's eye
(:class:`~invglare.models.kakimoto.KakimotoGlare` of an
:class:`~invglare.aperture.eye.EyeAperture`, :mod:`invglare.cie_study.setup`) is a
*diffraction* model: its PSF is ``|F[t_o P]|²`` of a rasterised pupil, so it describes
light only up to the alias-free angle of the raster, ``lambda / (2 · pitch)`` at the
shortest wavelength — 1.1° for a 3 mm pupil on 256 samples at 460 nm, 2.2° on 512.
Beyond that the model holds nothing, and what the CIE puts there (fundus reflection,
light through the eye wall, the wide-angle tail of the cornea and lens) is not
diffraction by anything the model rasterises. So the fit covers
**0.1° to the model's largest alias-free angle** (a safety factor 0.9 below it, and
inside the output field), and the report says how much of the CIE's light lies beyond.
No smooth wide-angle term is added: such a term would fit the CIE by construction and
say nothing about the eye's structures.

**What is fitted.** The radially averaged GSF of the model in logarithmically spaced
annuli, against the reference averaged over the same pixel centres
(:mod:`invglare.cie_study.annuli`). Residuals are ``log10(model) − log10(CIE)`` per
annulus, so every decade of angle and of level counts alike; they are minimised with
Levenberg–Marquardt (optimistix) over the latent parameters of an
:class:`invglare.fit.ParameterSpace` (logit transforms keep every value inside its
bounds), from a few starts. The solver's Jacobian is a central difference over ±0.1
latent units (±5-10 % of a count or radius), not the exact derivative: the derivative
with respect to a relaxed count is that of the one particle fading in, whose
interference with all the others (speckle) swamps the trend, and the solver stalls
where it starts (seen in practice; the profile's trend, which the finite difference
measures, is smooth).

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
```
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from jaxtyping import Float

from invglare.cie_study.annuli import RadialBins, cie_target, model_gsf
from invglare.cie_study.setup import CieFitSetup, build_fit_model
from invglare.errors import ConfigError

__all__ = ["FD_STEP", "CieFitResult", "fit_cie", "fit_radial_gsf", "parse_cie_spec"]

#: Step (latent units) of the finite-difference Jacobian of a fit (see `_prepare`).
FD_STEP = 0.1


@dataclasses.dataclass(eq=False)
class CieFitResult:
    """A fit of the eye's radial GSF to a target (the CIE function or a synthetic one).

    **Fields:** `label`; `age`, `pigmentation` (``None`` for a non-CIE target);
    `values` (``{path: value}``); `theta_deg`, `target_gsf`, `model_gsf` (per annulus);
    `residual_log10` (``log10(model / target)`` per annulus); `rms_log10`, `max_log10`;
    `loss`; `converged`; `n_steps`; `starts` (final loss of every start); `seconds`;
    `setup`; `initial_gsf` (the first start's GSF); `blocked_fraction` (of the pupil's
    light, stopped by the fitted particles: ``1 − Σ P² / Σ opening²``); `energy_beyond`
    (fraction of the CIE's light beyond the fitted range within 100°, or ``None``);
    `stderr` (``{path: standard error}`` from the scatter between eyes with the fitted
    parameters, when the setup simulates `draws`; else empty) and `draw_sd_log10` (that
    scatter per annulus, log10 units).
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
    stderr: dict[str, float] = dataclasses.field(default_factory=dict)
    draw_sd_log10: np.ndarray | None = None

    def summary(self) -> str:
        lines = [
            f"{self.label}: rms {self.rms_log10:.3f}, max {self.max_log10:.3f} log10 units "
            f"over {self.theta_deg[0]:.3g}-{self.theta_deg[-1]:.3g} deg "
            f"(solver {'converged' if self.converged else 'stopped at max_steps'}, "
            f"{self.n_steps} steps, {self.seconds:.0f} s); the particles block "
            f"{100 * self.blocked_fraction:.0f} % of the pupil's light"
        ]
        lines += [
            f"  {path} = {value:.5g}"
            + (f" ± {self.stderr[path]:.2g} (between eyes)" if path in self.stderr else "")
            for path, value in self.values.items()
        ]
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
            "stderr": self.stderr,
            "draw_sd_log10": None if self.draw_sd_log10 is None else self.draw_sd_log10.tolist(),
        }


@dataclasses.dataclass(frozen=True, eq=False)
class _Prepared:
    """What every fit with one setup shares: model, space, annuli and compiled functions."""

    model: Any
    space: Any
    bins: RadialBins
    solve: Callable
    residuals: Callable
    draws: Callable  # (latent, model, keys) -> log10 GSF of each redrawn eye
    jacobian: Callable  # (latent, args) -> the trend Jacobian of the residuals


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

    from invglare.fit.redraw import redraw

    model, space = build_fit_model(setup)
    bins = RadialBins.build(
        setup.npix, setup.pixel_scale_deg, setup.theta_min_deg, setup.max_angle_deg(),
        setup.n_bins,
    )  # fmt: skip

    def exact(latent, model, log_target, inv_sd):
        fitted = space.apply(model, space.from_latent(latent))
        gsf = model_gsf(fitted, bins)
        # A floor far below any GSF the model makes keeps log() finite if a bin empties.
        return (jnp.log10(jnp.maximum(gsf, 1e-12)) - log_target) * inv_sd

    # The exact derivative with respect to a relaxed count is the effect of the one
    # particle fading in, and its interference with all the others (speckle) swamps the
    # trend: the solver then stalls where it starts. So the Jacobian is a central
    # difference over +-FD_STEP latent units (about +-5-10 % of a count or a radius),
    # the slope of the profile's trend, which is what a fit of a statistic needs.
    @jax.custom_jvp
    def smoothed(latent, model, log_target, inv_sd):
        return exact(latent, model, log_target, inv_sd)

    @smoothed.defjvp
    def _smoothed_jvp(primals, tangents):
        latent, model, log_target, inv_sd = primals
        d_latent = tangents[0]  # the model and the target are data: their tangents are 0
        steps = FD_STEP * jnp.eye(latent.shape[0], dtype=latent.dtype)
        probes = jnp.concatenate([latent + steps, latent - steps])
        values = jax.vmap(lambda y: exact(y, model, log_target, inv_sd))(probes)
        n = latent.shape[0]
        jac = (values[:n] - values[n:]).T / (2.0 * FD_STEP)  # (n_bins, p)
        return exact(latent, model, log_target, inv_sd), jac @ d_latent

    def residuals(latent, args):
        model, log_target, inv_sd = args
        return smoothed(latent, model, log_target, inv_sd)

    # Tolerances on the latent step and the loss: 1e-4 is far below what matters in
    # log10 units (0.01 is a 2 % change of the GSF).
    solver = optx.LevenbergMarquardt(rtol=1e-4, atol=1e-6)

    @eqx.filter_jit
    def solve(y0, args):
        sol = optx.least_squares(
            residuals, solver, y0, args=args, max_steps=setup.max_steps, throw=False
        )
        return sol.value, sol.result == optx.RESULTS.successful, sol.stats["num_steps"]

    def draw_log_gsf(latent, model, key):
        fitted = space.apply(model, space.from_latent(latent))
        return jnp.log10(jnp.maximum(model_gsf(redraw(fitted, key), bins), 1e-12))

    def jacobian(latent, args):
        return jax.jacfwd(residuals)(latent, args)

    return _Prepared(
        model, space, bins, solve, eqx.filter_jit(residuals),
        eqx.filter_jit(lambda y, m, keys: jax.lax.map(lambda k: draw_log_gsf(y, m, k), keys)),
        eqx.filter_jit(jacobian),
    )  # fmt: skip


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
        log_target = jnp.log10(jnp.asarray(target))
        args = (prep.model, log_target, jnp.ones_like(log_target))
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
        stderr, draw_sd = {}, None
        if setup.draws:
            value, ok, steps, stderr, draw_sd = _refit_with_draw_scatter(prep, setup, value, args)
            r = np.asarray(prep.residuals(value, args))
            loss = float(np.sum(r * r))
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
        stderr=stderr,
        draw_sd_log10=draw_sd,
    )


def _refit_with_draw_scatter(prep: _Prepared, setup: CieFitSetup, value, args):
    """Refit weighting each annulus by the scatter between eyes, and the errors it causes.

    `setup.draws` eyes with the fitted parameters (the model with its particles drawn
    anew, :func:`invglare.fit.redraw.redraw`) give the draw-to-draw standard deviation
    ``sd`` of the log10 GSF per annulus. The target is one eye and the model another, so
    their log ratio scatters by ``sqrt(2) sd``: the fit is repeated from `value` with the
    residuals divided by that, and the covariance of the estimate is that of a linearised
    bootstrap over the simulated eyes (``pinv(J)`` applied to each eye's standardised
    deviation, twice: the target's draw and the model's), in the latent space, mapped to
    the physical values by the transforms' derivatives.

    **Returns:** ``(latent, converged, steps, {path: stderr}, sd per annulus)``.
    """
    import jax
    import jax.numpy as jnp

    model, log_target, _ = args
    keys = jax.random.split(jax.random.key(setup.seed + 7919), int(setup.draws))
    sd = np.std(np.asarray(prep.draws(value, model, keys)), axis=0, ddof=1)
    inv_pair = jnp.asarray(1.0 / (math.sqrt(2.0) * np.maximum(sd, 1e-6)))
    weighted = (model, log_target, inv_pair)
    value, ok, steps = prep.solve(value, weighted)
    eyes = np.asarray(prep.draws(value, model, keys))
    sd = np.std(eyes, axis=0, ddof=1)
    jac = np.asarray(prep.jacobian(value, weighted), dtype=np.float64)
    moves = ((eyes - eyes.mean(axis=0)) * np.asarray(inv_pair)) @ np.linalg.pinv(jac).T
    cov_z = 2.0 * np.atleast_2d(np.cov(moves, rowvar=False))
    space = prep.space
    d = np.asarray(space.jacobian_diag(value), dtype=np.float64)
    var = d * d * np.diag(cov_z)
    stderr = {p: float(np.sqrt(v)) for p, v in zip(space.paths, var, strict=True)}
    return value, bool(ok), int(steps), stderr, sd


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
