"""The fit benchmark: invglare's Levenberg–Marquardt against finite-difference least squares.

A synthetic problem (a :class:`FitProblem`), solved side by side in the same process; the
benchmark's own is :data:`DAYLIGHT_EYE`:

- **the photo**: the daylight eye of ``examples/eye_daylight.toml`` (Kakimoto glare, fixed
  mask, 550 nm) on an `npix` x `npix` grid, turned into counts by an
  :class:`~invglare.fit.Observation` (flux 1e7, background 20, gain 2, read noise 3) and
  sampled with a fixed key;
- **the free parameters**: pupil diameter, upper-lash count, source flux and background;
- **invglare**: :func:`invglare.fit.fit` in float64 (LM with forward-mode Jacobians),
  with its compile and solve times reported apart;
- **scipy**: ``scipy.optimize.least_squares(method="trf", jac="2-point")`` on the *same*
  jitted residual function (:func:`invglare.fit.make_residual_fn`) from the same start,
  in float64; then the same in float32, once with scipy's default difference step (made
  for float64) and once with the float32-sized step ``sqrt(eps_float32)``. The float32
  model fits a photo made by the float32 model: the eye draws its random elements in
  its own dtype, and `jax.random` draws differ between float32 and float64 for one key,
  so the float32 eye is a different eye.

"Time to the same loss" is measured for both solvers from the moment their compiled
residuals start running (compilation excluded on both sides; reported separately): for
scipy from a log of every residual evaluation, for invglare from host timestamps of its
accepted steps. The target is the lower of the two float64 final losses, relaxed by
:data:`LOSS_RTOL`.
"""

from __future__ import annotations

import copy
import dataclasses
import datetime as dt
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from invglare.bench.timing import load_1m, measure
from invglare.errors import ConfigError

DIAMETER = "model.aperture.pupil.diameter_mm"
LASHES = "model.aperture.upper_lashes.count"
#: Two losses are "the same" within this relative difference (a chi-square of 16 000 to 0.016).
LOSS_RTOL = 1e-6
#: The same for the float32 runs: a float32 sum of 16 000 squares resolves about 1e-6 of
#: itself, and their reference is only close to (not at) their own optimum.
LOSS_RTOL_32 = 1e-4
NOISE = {"gain": 2.0, "read_noise": 3.0}

DEFAULT_CONFIG = Path(__file__).resolve().parents[2] / "examples" / "eye_daylight.toml"


class FreeParameter(NamedTuple):
    """A parameter both solvers fit: its bounds, the photo's value and the common start."""

    path: str
    lower: float
    upper: float
    truth: float
    start: float
    short: str


@dataclasses.dataclass(frozen=True)
class FitProblem:
    """A synthetic fit problem: a model config, its free parameters and the photo's light.

    Flux and background are always free (nuisance parameters starting from the photo's own
    estimates, as a user's fit would).
    """

    name: str
    config_path: Path
    free: tuple[FreeParameter, ...]
    #: What is free, in words, for bench.md.
    summary: str
    #: Aperture window (mm) when the config gives none: room for every trial pupil, so
    #: that the truth and the trials share one grid.
    window_mm: float
    flux: float = 1e7
    background: float = 20.0

    @property
    def truth(self) -> dict[str, float]:
        return {p.path: p.truth for p in self.free} | {
            "obs.flux": self.flux,
            "obs.background": self.background,
        }

    @property
    def start(self) -> dict[str, float]:
        return {p.path: p.start for p in self.free}

    def short(self, path: str) -> str:
        names = {p.path: p.short for p in self.free}
        return names.get(path, {"obs.flux": "flux", "obs.background": "bg"}.get(path, path))


#: The daylight eye of examples/eye_daylight.toml (diameter and lash count as there). The
#: lash count starts at a non-integer: a relaxed count has a zero derivative at every
#: integer (:mod:`invglare.aperture.eye`), so a local solver moves it within one integer
#: step, not across several. Its upper bound is the example's ``n_max``.
DAYLIGHT_EYE = FitProblem(
    name="fit_daylight_eye",
    config_path=DEFAULT_CONFIG,
    free=(
        FreeParameter(DIAMETER, 2.0, 4.0, truth=3.0, start=3.4, short="D"),
        FreeParameter(LASHES, 0.0, 48.0, truth=40.0, start=39.4, short="lashes"),
    ),
    summary="pupil diameter, upper-lash count (start 39.4 for a truth of 40), flux, background",
    window_mm=4.2,
)

#: The fit benchmarks by name, selectable like the per-size cases (``invglare bench fit``).
FIT_PROBLEMS = {p.name: p for p in (DAYLIGHT_EYE,)}
FIT_CASES = tuple(FIT_PROBLEMS)


def _config(problem: FitProblem, npix: int) -> dict[str, Any]:
    from invglare.files.toml import load_toml

    path = Path(problem.config_path)
    if not path.is_file():
        raise ConfigError(
            f"the fit benchmark {problem.name} builds its model from {path}, which does not exist"
        )
    config = copy.deepcopy(load_toml(path))
    model = config.setdefault("model", {})
    model["aperture_npix"] = npix
    # Without a fixed window, the window would follow the start's pupil and differ from
    # the truth's.
    model.setdefault("window_mm", problem.window_mm)
    config.setdefault("output", {})["npix"] = npix
    # The fit needs a monochrome PSF.
    config.setdefault("spectrum", {})["wavelengths_nm"] = 550.0
    return config


def _problem(problem: FitProblem, config: dict[str, Any]):
    """Space, template and target in the current default dtype (photo from a fixed key)."""
    from invglare.config.model import build_model
    from invglare.fit import Forward, Observation, Parameter, ParameterSpace

    model = build_model(config)
    free = [Parameter(p.path, p.lower, p.upper, init=p.start) for p in problem.free]
    shape = ParameterSpace(free)
    light = Observation(flux=problem.flux, background=problem.background, **NOISE)
    truth = shape.apply(Forward(model, light), shape.values_from(problem.truth))
    psf = eqx.filter_jit(lambda m: m())(truth.model)
    target = np.asarray(light.sample(jax.random.key(1), psf), dtype=np.float64)
    obs = Observation.from_target(target, **NOISE)
    template = shape.apply(Forward(model, obs), shape.values_from(problem.start))
    space = ParameterSpace(
        free,
        nuisance=[
            Parameter("obs.flux", 0.0, math.inf, init=float(obs.flux)),
            Parameter("obs.background", -100.0, 1000.0, init=float(obs.background)),
        ],
    )
    return space, template, target


class _LossLog:
    """Host-side log of (seconds since start, loss) for every residual evaluation."""

    def __init__(self):
        self.t0 = time.perf_counter()
        self.entries: list[tuple[float, float]] = []

    def add(self, loss: float) -> None:
        self.entries.append((time.perf_counter() - self.t0, loss))

    def time_to(self, target: float) -> float | None:
        for t, loss in self.entries:
            if loss <= target:
                return t
        return None


def _scipy_run(
    residual: Callable[[Float[Array, " p"]], Float[Array, " n"]],
    z0: Float[np.ndarray, " p"],
    dtype,
    diff_step: float | None,
    max_nfev: int | None,
) -> tuple[dict[str, Any], _LossLog]:
    """`least_squares` ('trf', '2-point') on a compiled residual evaluated in `dtype`."""
    from scipy.optimize import least_squares

    log = _LossLog()

    def fun(z: Float[np.ndarray, " p"]) -> Float[np.ndarray, " n"]:
        r = np.asarray(residual(jnp.asarray(z, dtype=dtype)), dtype=np.float64)
        log.add(float(r @ r))
        return r

    log.t0 = time.perf_counter()
    sol = least_squares(
        fun, z0, method="trf", jac="2-point", diff_step=diff_step, max_nfev=max_nfev
    )
    wall = time.perf_counter() - log.t0
    loss0 = log.entries[0][1]
    final = float(2.0 * sol.cost)
    return {
        "wall_s": wall,
        "n_evaluations": len(log.entries),
        "nfev": int(sol.nfev),
        "njev": int(sol.njev) if sol.njev is not None else None,
        "start_loss": loss0,
        "final_loss": final,
        "latent_moved": float(np.max(np.abs(sol.x - z0))),
        "status": int(sol.status),
        "message": str(sol.message),
        "diff_step": diff_step,
        "x": sol.x,
    }, log


def _residual_jit(fn) -> Callable[[Float[Array, " p"]], Float[Array, " n"]]:
    """The residuals as one compiled function of the latent vector (`fn`'s data as inputs)."""
    compiled = eqx.filter_jit(lambda f, z: f(z, None))
    return lambda z: compiled(fn, z)


def run_fit_benchmark(
    problem: FitProblem = DAYLIGHT_EYE,
    npix: int = 128,
    *,
    max_steps: int = 256,
    scipy_max_nfev: int | None = None,
    float32: bool = True,
) -> dict[str, Any]:
    """Run one fit problem with invglare and with scipy; return one record.

    **Arguments:**

    - `problem`: the model and its free parameters (:data:`DAYLIGHT_EYE` by default).
    - `npix`: photo size (and aperture raster size), pixels.
    - `max_steps`: invglare's step budget; `scipy_max_nfev`: scipy's (None: its default,
      100 x the number of parameters). Small values are for testing the plumbing.
    - `float32`: also run the float32 finite-difference fits.

    **Returns:** a JSON-ready dict: the problem, ``invglare`` (compile / solve seconds,
    final loss, steps, time to the target loss), ``scipy_float64`` and, with `float32`,
    ``scipy_float32_default_step`` and ``scipy_float32_eps32_step`` (wall seconds,
    evaluations, final loss, time to the target), the per-evaluation costs, and the
    speed ratios.
    """
    from invglare.fit import FitProgress, fit, make_residual_fn
    from invglare.fit.solve import _jacobian_and_residuals

    if int(npix) != npix or npix < 16:
        raise ConfigError(f"fit benchmark npix must be an integer >= 16, got {npix!r}")
    config = _config(problem, int(npix))
    truth = problem.truth
    record: dict[str, Any] = {
        "case": problem.name,
        "kind": "fit",
        "npix": int(npix),
        "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "load_1m_start": load_1m(),
        "problem": {
            "truth": truth,
            "start": problem.start,
            "free": problem.summary,
            "short": {path: problem.short(path) for path in truth},
            "noise": dict(NOISE),
            "views": {"pixels": 1.0},
            "loss_rtol": LOSS_RTOL,
        },
    }

    with jax.enable_x64(True):
        t0 = time.perf_counter()
        space, template, target = _problem(problem, config)
        record["setup_s"] = time.perf_counter() - t0
        prop = template.model.propagator
        record["problem"]["model"] = (
            f"{Path(problem.config_path).name}: {type(template.model).__name__}, 550 nm, "
            f"{npix}x{npix} photo at "
            f"{float(prop.output.pixel_scale_deg):.4g} deg/px, {prop.grid.npix}x"
            f"{prop.grid.npix} aperture raster over {float(prop.grid.width_mm):.3g} mm, "
            f"{prop.method.upper()} propagation"
        )
        starts = space.as_dict(space.from_latent(space.initial_latent()))

        # --- invglare LM, float64 -------------------------------------------------------
        def run_lm():
            stamps: list[tuple[float, float]] = []

            def progress(p: FitProgress) -> None:
                stamps.append((time.perf_counter(), p.loss))

            res = fit(
                space,
                template,
                target,
                {"pixels": 1.0},
                starts=starts,
                max_steps=max_steps,
                truth=truth,
                progress=progress,
            )
            return res, stamps

        # The first run compiles and is the compiled program's first execution (slower:
        # fresh buffers and code pages); the second hits the compile cache and is timed
        # warm, like scipy's residual below (compiled, then evaluated 10 times first).
        first, _ = run_lm()
        res, stamps = run_lm()
        fn = make_residual_fn(space, template, target, {"pixels": 1.0})
        z_best = space.to_latent(jnp.asarray([res.values[p] for p in space.paths]))
        # The LM's Jacobian at the optimum (`measure` compiles it on its first call, untimed).
        jac = measure(lambda: _jacobian_and_residuals(fn, z_best), 5, budget_s=5.0)
        lm = {
            "compile_s": first.timing_s["compile"],
            "first_solve_s": first.timing_s["solve"],
            "solve_s": res.timing_s["solve"],
            "total_s": first.timing_s["total"],
            "final_loss": res.loss,
            "n_steps": res.n_steps,
            "n_accepted": max(len(stamps) - 1, 0),
            "converged": res.converged,
            "message": res.message,
            "values": res.values,
            "jacobian_ms": jac.median_ms,
        }

        # --- scipy least_squares, float64, same compiled residual ------------------------
        residual64 = _residual_jit(fn)
        z0 = np.asarray(space.initial_latent(), dtype=np.float64)
        t0 = time.perf_counter()
        jax.block_until_ready(residual64(jnp.asarray(z0)))
        compile64 = time.perf_counter() - t0
        eval64 = measure(lambda: residual64(jnp.asarray(z0)), 10, budget_s=5.0)
        sp64, log64 = _scipy_run(residual64, z0, jnp.float64, None, scipy_max_nfev)
        sp64["compile_s"] = compile64
        sp64["residual_ms"] = eval64.median_ms
        sp64["values"] = space.as_dict(space.from_latent(jnp.asarray(sp64.pop("x"))))

    target_loss = min(lm["final_loss"], sp64["final_loss"]) * (1.0 + LOSS_RTOL)
    lm["time_to_target_s"] = _lm_time_to(stamps, target_loss, lm)
    sp64["time_to_target_s"] = log64.time_to(target_loss)
    record["target_loss"] = target_loss
    record["invglare"] = lm
    record["scipy_float64"] = sp64

    if float32:
        # --- the same in float32: the rendering precision, where FD steps break down ---
        # Random elements (an eye's lashes and particles) are drawn in the model's dtype,
        # and jax.random gives different numbers for float32 and float64 from one key: the
        # float32 model is a different eye. So it fits its own photo (same truth, same
        # noise key), and its reference loss is at invglare's float64 solution (close to
        # its own optimum: the truth values are the same).
        space32, template32, target32 = _problem(problem, config)
        fn32 = make_residual_fn(space32, template32, target32, {"pixels": 1.0})
        residual32 = _residual_jit(fn32)
        z0_32 = np.asarray(space32.initial_latent(), dtype=np.float64)
        t0 = time.perf_counter()
        jax.block_until_ready(residual32(jnp.asarray(z0_32, jnp.float32)))
        compile32 = time.perf_counter() - t0
        eval32 = measure(lambda: residual32(jnp.asarray(z0_32, jnp.float32)), 10, budget_s=5.0)
        best = np.asarray([lm["values"][p] for p in space32.paths])
        r_ref = np.asarray(residual32(space32.to_latent(jnp.asarray(best, jnp.float32))), float)
        reference32 = float(r_ref @ r_ref)
        target32 = reference32 * (1.0 + LOSS_RTOL_32)
        record["float32_reference_loss"] = reference32
        record["float32_target_loss"] = target32
        eps32 = float(np.sqrt(np.finfo(np.float32).eps))
        for key, step in (
            ("scipy_float32_default_step", None),
            ("scipy_float32_eps32_step", eps32),
        ):
            run, log = _scipy_run(residual32, z0_32, jnp.float32, step, scipy_max_nfev)
            run["compile_s"] = compile32
            run["residual_ms"] = eval32.median_ms
            run["values"] = space32.as_dict(space32.from_latent(jnp.asarray(run.pop("x"))))
            run["time_to_target_s"] = log.time_to(target32)
            run["reached_target"] = run["time_to_target_s"] is not None
            record[key] = run

    record["ratios"] = _ratios(lm, sp64, len(truth))
    record["load_1m_end"] = load_1m()
    return record


def _lm_time_to(stamps: list[tuple[float, float]], target: float, lm: dict) -> float | None:
    """Seconds from the start of the solve to the first accepted step at or below `target`.

    The stamps are host times of the progress reports; the first report (the start's
    loss) comes one step into the solve, so one average step is added.
    """
    if not stamps:
        return None
    step = lm["solve_s"] / max(lm["n_steps"], 1)
    t_first = stamps[0][0]
    for t, loss in stamps:
        if loss <= target:
            return t - t_first + step
    # The final loss is evaluated after the last accepted step.
    return lm["solve_s"] if lm["final_loss"] <= target else None


def _ratios(lm: dict, sp: dict, n_free: int) -> dict[str, float | None]:
    """scipy over invglare: > 1 means invglare is faster."""

    def ratio(a, b):
        return a / b if a is not None and b else None

    return {
        "time_to_target": ratio(sp["time_to_target_s"], lm["time_to_target_s"]),
        "full_solve": ratio(sp["wall_s"], lm["solve_s"]),
        "with_compile": ratio(sp["wall_s"] + sp["compile_s"], lm["solve_s"] + lm["compile_s"]),
        "per_iteration_cost": ratio(sp["residual_ms"] * (1 + n_free), lm["jacobian_ms"]),
    }


def fit_markdown(record: dict[str, Any]) -> list[str]:
    """The fit benchmark's section of bench.md."""
    lm, sp = record["invglare"], record["scipy_float64"]
    short = record["problem"].get("short", {})

    def values(v: dict[str, float]) -> str:
        return ", ".join(f"{short.get(k, k)} {x:.5g}" for k, x in v.items())

    def s(x, fmt=".2f"):
        return "—" if x is None else format(x, fmt)

    lines = [
        f"## Fit: {record['case']} ({record['npix']}² photo)",
        "",
        f"Measured {record['date']}. {record['problem']['model']}. Free: "
        f"{record['problem'].get('free', ', '.join(record['problem']['truth']))}; truth "
        f"{values(record['problem']['truth'])}; pixel view (noise-normalised "
        f"residuals). Load (1 min) {record['load_1m_start']} at the start, "
        f"{record['load_1m_end']} at the end.",
        "",
        "| solver | dtype | compile s | solve / wall s | time to target s | evaluations "
        "| final loss | stopped because |",
        "|---|---|---:|---:|---:|---:|---:|---|",
        f"| invglare LM (fit) | float64 | {s(lm['compile_s'], '.1f')} | {s(lm['solve_s'])} "
        f"| {s(lm['time_to_target_s'])} | {lm['n_steps']} steps ({lm['n_accepted']} accepted) "
        f"| {lm['final_loss']:.6g} | {_short(lm['message'])} |",
    ]
    runs = [("scipy trf, 2-point FD", "float64", sp)]
    for key, label in (
        ("scipy_float32_default_step", "scipy trf, 2-point FD, default step"),
        ("scipy_float32_eps32_step", "scipy trf, 2-point FD, step sqrt(eps32)"),
    ):
        if key in record:
            runs.append((label, "float32", record[key]))
    for label, dtype, run in runs:
        lines.append(
            f"| {label} | {dtype} | {s(run['compile_s'], '.1f')} | {s(run['wall_s'])} "
            f"| {s(run['time_to_target_s'])} | {run['n_evaluations']} "
            f"(nfev {run['nfev']}, njev {run['njev']}) | {run['final_loss']:.6g} "
            f"| {_short(run['message'])} |"
        )
    r = record["ratios"]
    lines += [
        "",
        f"Target loss {record['target_loss']:.6g} (the lower float64 final loss + "
        f"{LOSS_RTOL:g} relative). Speed, scipy time over invglare time (> 1: invglare "
        f"faster): to the target **{s(r['time_to_target'])}**, full solves "
        f"{s(r['full_solve'])}, including compilation {s(r['with_compile'])}. Per "
        f"iteration: a forward-mode Jacobian with residuals takes {lm['jacobian_ms']:.1f} ms, "
        f"a residual {sp['residual_ms']:.1f} ms, so one 2-point Jacobian (5 residuals) over "
        f"one autodiff Jacobian is {s(r['per_iteration_cost'])}. Iterations: invglare "
        f"{lm['n_steps']} steps of which {lm['n_accepted']} accepted, each computing a "
        f"Jacobian; scipy {sp['njev']} Jacobians and {sp['nfev']} other residuals. "
        f"`fit()` took {lm['total_s']:.1f} s end to end (besides compile and solve: setting "
        "up the residuals and compiling the covariance's Jacobian and the prediction).",
        "",
        "Both solvers are timed warm: scipy's residual after its compiling call and ten "
        "timed evaluations, invglare's solve on a second `fit()` from the same start (the "
        "compiled solve cached). The first run of the freshly compiled solve took "
        f"{s(lm.get('first_solve_s'))} s (a program's first execution also pays for its "
        "buffers and code pages).",
        "",
        f"Start loss {sp['start_loss']:.6g}. Fitted values: invglare "
        + values(lm["values"])
        + "; scipy float64 "
        f"{values(sp['values'])}.",
    ]
    if "scipy_float32_default_step" in record:
        d = record["scipy_float32_default_step"]
        e = record["scipy_float32_eps32_step"]
        lines += [
            "",
            "float32 finite differences (their own photo: a float32 model draws its random "
            "elements, such as an eye's lashes, in float32, which jax.random makes a "
            "different model from the same key; reference loss "
            f"{record['float32_reference_loss']:.6g} at "
            "invglare's float64 solution, target "
            f"{record['float32_target_loss']:.6g}): with scipy's default step (sized for "
            f"float64, ~1.5e-8 relative) the loss went from {d['start_loss']:.6g} to "
            f"{d['final_loss']:.6g} (latent moved by {d['latent_moved']:.3g}, "
            f"{'reached' if d['reached_target'] else 'did not reach'} the target); with "
            f"the float32 step sqrt(eps32) = 3.5e-4 it ended at {e['final_loss']:.6g} after "
            f"{e['n_evaluations']} residuals "
            f"({'reached' if e['reached_target'] else 'did not reach'} the target).",
        ]
    return lines


def _short(message: str) -> str:
    return message.split(";")[0].split(" (")[0].replace("|", "/")


def as_json(record: dict[str, Any]) -> dict[str, Any]:
    """The record with NumPy scalars made plain (for bench.json)."""
    return jax.tree_util.tree_map(lambda x: x.item() if isinstance(x, np.generic) else x, record)


__all__ = [
    "DAYLIGHT_EYE",
    "FIT_CASES",
    "FIT_PROBLEMS",
    "FitProblem",
    "FreeParameter",
    "as_json",
    "fit_markdown",
    "run_fit_benchmark",
]
