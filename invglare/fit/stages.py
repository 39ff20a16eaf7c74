"""Staged fits: a scan across the bounds, stages that seed each other, held parameters.

A photo's pixel-wise objective is often multimodal (a pupil's Airy rings, lash streaks
that speckle by their random draw), so a fit runs as a plan:

1. optionally a **scan**: points across the bounds scored by the first stage's loss (no
   solving), the best `n_starts` kept as starts; with the flux free, each point gets the
   flux that matches the photo's unclipped pixels first (:func:`scan`);
2. **stages** (:class:`Stage`) before the final fit, each on views that do not depend on
   the random draw (radial profile, angular energy), from the best result of the one
   before, with some parameters **held** at their start values (:func:`hold`); a stage
   may **branch** its best result into several starts of the next, one per integer value
   of a relaxed count near it (:func:`branched_starts`);
3. the **final** fit, on the final views, from the best result so far.

:func:`fit_staged` runs the plan and returns one :class:`~invglare.fit.FitResult`
carrying every stage's record. Nothing here prints: progress reaches the caller through
callbacks (:class:`~invglare.fit.FitProgress` per accepted solver step,
:class:`ScanProgress` per scored point, :class:`StageDone` after each stage).

**Example:**

```python
import jax
from invglare.config.fit import load_fit

with jax.enable_x64(True):
    setup = load_fit("fits/eye_daylight.toml")
    result = setup.fit()                 # = fit_staged(setup.space, setup.forward, ...)
print(result.summary())
```
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from invglare.errors import ConfigError
from invglare.fit.draw_scatter import scatter_covariance, scatter_options
from invglare.fit.observation import Forward
from invglare.fit.params import ParameterSpace
from invglare.fit.result import FitResult
from invglare.fit.solve import FitProgress, fit, fit_many
from invglare.fit.trust import flags_summary, parameter_flags
from invglare.fit.views import ResidualFn, make_residual_fn


@dataclasses.dataclass(frozen=True)
class Stage:
    """A stage run before the final fit: its views, step budget and the paths it holds fixed.

    Stochastic structure (lash and needle positions) makes the pixel-wise objective
    multimodal; a first stage on views that do not depend on the random draw (radial
    profile, angular energy) brings the starts into the right basin for the final
    pixel-wise stage. Such views hardly constrain some nuisances (the source centre):
    `fixed` holds them at the values the stage starts from.

    A relaxed count (an eye's lashes) that such views place only to within a lash or two
    still leaves the pixel-wise stage in the wrong basin: each integer count draws other
    lashes. `branch` ``((path, offsets),)`` starts the next stage once per offset, from
    the stage's best result with `path` rounded to an integer plus the offset (see
    :func:`branched_starts`); the next stage keeps the best.

    **Example:** ``Stage({"radial": 1.0, "angular": 1.0}, 40, ("obs.dx_px", "obs.dy_px"),
    (("model.aperture.upper_lashes.count", (-1, 0, 1)),))``.
    """

    views: dict[str, float]
    max_steps: int
    fixed: tuple[str, ...] = ()
    branch: tuple[tuple[str, tuple[int, ...]], ...] = ()


class ScanProgress(NamedTuple):
    """A scan's progress: `done` of `total` points scored by `views` (first report: 0)."""

    done: int
    total: int
    views: tuple[str, ...]


class StageDone(NamedTuple):
    """A stage of a staged fit finished (reported when the plan has more than one fit).

    `number` counts the stage records so far, `views` are the stage's, `loss` its best,
    `best_start` the index of the first stage's start the best result descends from,
    `values` the parameters of interest there.
    """

    number: int
    views: dict[str, float]
    loss: float
    best_start: int
    values: dict[str, float]


def fit_staged(
    space: ParameterSpace,
    forward: Forward,
    target: Float[ArrayLike, "h w"],
    views: Mapping[str, float],
    starts: Float[ArrayLike, "n p"],
    *,
    stages: Sequence[Stage] = (),
    scan_points: Float[ArrayLike, "m p"] | None = None,
    view_options: Mapping[str, Mapping[str, Any]] | None = None,
    truth: Mapping[str, float] | None = None,
    final: bool = True,
    resume: FitResult | None = None,
    progress: Callable[[FitProgress], None] | None = None,
    scan_progress: Callable[[ScanProgress], None] | None = None,
    stage_done: Callable[[StageDone], None] | None = None,
    **solver: Any,
) -> FitResult:
    """Run a staged fit: an optional scan, the `stages` in order, then the final fit.

    **Arguments:**

    - `space`, `forward`, `target`: as for :func:`invglare.fit.fit`.
    - `views`: ``{name: weight}`` of the final fit.
    - `starts`: ``(n, p)`` physical starts of the first stage (order of `space.paths`).
    - `stages`: the :class:`Stage` s before the final fit (often none).
    - `scan_points`: ``(m, p)`` points to score by the first stage's loss; the best
      ``n`` of them replace `starts` (see :func:`scan`). None: no scan.
    - `view_options`: ``{view: {option: value}}`` of every view used.
    - `truth`: ``{path: value}`` where known (carried into the result).
    - `final`: False runs the stages before the final one only (there must be some);
      pass that result as `resume` to run the final fit from its best values later
      (a sweep over discrete choices refines only the most promising choice so).
    - `progress`: receives every :class:`~invglare.fit.FitProgress`, numbered as
      stages of one run; `scan_progress` and `stage_done` receive
      :class:`ScanProgress` and :class:`StageDone`.
    - `solver`: the remaining keyword arguments of :func:`invglare.fit.fit`
      (``solver``, ``max_steps``, ``rtol``, ``atol``, ``coarse_to_fine``,
      ``refine_top``, ``covariance_scale``, ``batch``); a stage's `max_steps` wins.

    **Returns:** the last fit's :class:`~invglare.fit.FitResult` with the earlier
    stages' records prepended to its `stages` (each record names its views; `origin`
    indexes the first stage's starts; the first holds the scan's record), its `starts`
    and `best_start` those of the first stage, and its step count and timings summed.

    **Example:**

    ```python
    result = fit_staged(space, forward, photo, {"pixels": 1.0}, starts,
                        stages=[Stage({"radial": 1.0}, 40)])
    ```
    """
    plan = _Plan(
        space, forward, target, views, starts, stages=stages, scan_points=scan_points,
        view_options=view_options, truth=truth, final=final, resume=resume,
        progress=progress, scan_progress=scan_progress, stage_done=stage_done,
    )  # fmt: skip
    for j in range(len(plan.steps)):
        sub, template, free_starts, kwargs = plan.step(j)
        result = fit(sub, template, target, plan.views(j), starts=free_starts,
                     n_starts=free_starts.shape[0], **{**solver, **kwargs})  # fmt: skip
        plan.step_done(j, result)
    return plan.result()


def fit_staged_many(
    photos: Sequence[Mapping[str, Any]],
    *,
    stages: Sequence[Stage] = (),
    view_options: Mapping[str, Mapping[str, Any]] | None = None,
    **solver: Any,
) -> list[FitResult]:
    """:func:`fit_staged` for several photos of one structure, each plan step one
    vmapped solve over the photos (:func:`invglare.fit.solve.fit_many`).

    **Arguments:**

    - `photos`: one mapping per photo with the per-photo arguments of :func:`fit_staged`:
      ``space``, ``forward``, ``target``, ``views``, ``starts`` and optionally
      ``scan_points``, ``truth``, ``progress``, ``scan_progress``, ``stage_done``. Every
      photo has the same paths, bounds, views and number of starts (one fit config).
    - `stages`, `view_options`, `solver`: shared, as for :func:`fit_staged`.

    **Returns:** one :class:`~invglare.fit.FitResult` per photo; each equals
    :func:`fit_staged`'s for that photo up to the rounding of batched arithmetic (the
    scan scores each photo's points apart).
    """
    plans = [
        _Plan(
            p["space"], p["forward"], p["target"], p["views"], p["starts"], stages=stages,
            scan_points=p.get("scan_points"), view_options=view_options, truth=p.get("truth"),
            progress=p.get("progress"), scan_progress=p.get("scan_progress"),
            stage_done=p.get("stage_done"),
        )
        for p in photos
    ]  # fmt: skip
    own = ("truth", "progress", "view_options")  # per photo (measured scatter, say)
    for j in range(len(plans[0].steps)):
        steps = [plan.step(j) for plan in plans]
        shared = {key: v for key, v in steps[0][3].items() if key not in own}
        results = fit_many(
            [s[0] for s in steps], [s[1] for s in steps], [p["target"] for p in photos],
            plans[0].views(j), starts=[s[2] for s in steps],
            truths=[s[3]["truth"] for s in steps], progress=[s[3]["progress"] for s in steps],
            view_options=[s[3]["view_options"] for s in steps], **{**solver, **shared},
        )  # fmt: skip
        for plan, result in zip(plans, results, strict=True):
            plan.step_done(j, result)
    return [plan.result() for plan in plans]


#: Early stages only seed the next: no covariance or images (two compilations fewer), and a
#: pixel view there may stay in a variance-stabilised domain.
_EARLY = {"coarse_to_fine": (1,), "diagnostics": False, "final_likelihood": False}


class _Plan:
    """One photo's staged fit, step by step: :func:`fit_staged` and :func:`fit_staged_many`
    run each step's fit (for one photo, or several at once) and this keeps the books.

    A step is a stage of the plan, or one of the :data:`DRAW_ROUNDS` - 1 rounds before a
    stage whose views ask for draws (each measures the scatter between eyes at its start,
    the previous round's result, and fits: the offsets are right where they were measured).
    """

    def __init__(
        self, space, forward, target, views, starts, *, stages, scan_points, view_options,
        truth, final=True, resume=None, progress=None, scan_progress=None, stage_done=None,
    ):  # fmt: skip
        self.space, self.forward, self.target, self.truth = space, forward, target, truth
        self.view_options, self.progress, self.stage_done = view_options, progress, stage_done
        self.resume = resume
        pre = [(st.views, {**_EARLY, "max_steps": st.max_steps}, st.fixed) for st in stages]
        self.branches = [st.branch for st in stages] + [()]
        self.record = None
        if resume is None:
            self.plan = pre + ([(views, {}, ())] if final else [])
            if not self.plan:
                raise ConfigError("final=False needs stages to run; there are none")
            starts = np.asarray(starts)
            self.first = starts
            if scan_points is not None:
                first_views, _, first_fixed = self.plan[0]
                starts, self.record = scan(
                    space, forward, target, first_views, scan_points,
                    n=starts.shape[0], fixed=first_fixed, view_options=view_options,
                    progress=scan_progress,
                )  # fmt: skip
                self.first = np.asarray(self.record["starts"])
            # The first-stage start each start descends from.
            self.origin = np.arange(starts.shape[0])
            self.records: list[dict] = []
            self.n_steps = 0
            self.timing = {"compile": 0.0, "solve": 0.0, "total": 0.0}
        else:
            starts = np.asarray([[resume.values[p] for p in space.paths]])
            self.origin = np.asarray([resume.best_start])
            self.records = list(resume.stages)
            self.n_steps, self.timing = resume.n_steps, dict(resume.timing_s)
            self.plan = [(views, {}, ())]
        self.starts = starts
        self.interest = {q.path for q in space.parameters}
        self.held: dict[str, float] = {}
        self.last: FitResult | None = None
        # (stage, whether a round before it) per step.
        self.steps = [
            (k, r + 1 < rounds)
            for k, (v, _, _) in enumerate(self.plan)
            for rounds in [DRAW_ROUNDS if _draws(_subset(view_options, v)) else 1]
            for r in range(rounds)
        ]
        self.current: tuple | None = None  # the last step's space, template, views, options

    def views(self, j: int) -> Mapping[str, float]:
        """Step `j`'s views."""
        return self.plan[self.steps[j][0]][0]

    def step(self, j: int) -> tuple[ParameterSpace, Forward, np.ndarray, dict[str, Any]]:
        """Step `j`: its space (held paths removed), template, starts and fit settings."""
        k, is_round = self.steps[j]
        stage_views, overrides, fixed = self.plan[k]
        sub, template, free_starts, self.held = hold(self.space, self.forward, self.starts, fixed)
        options = _with_scatter(
            sub, template, self.target, stage_views, self.view_options, free_starts
        )
        self.current = (sub, template, stage_views, options)
        kwargs = {
            **overrides,
            **(_EARLY if is_round else {}),
            "truth": None if is_round else _subset(self.truth, sub.paths),
            "view_options": options,
            "progress": _numbered(self.progress, k, len(self.plan)),
        }
        return sub, template, free_starts, kwargs

    def step_done(self, j: int, result: FitResult) -> None:
        """Book step `j`'s result; the best of it starts the next step."""
        k, is_round = self.steps[j]
        stage_views = self.plan[k][0]
        paths = self.space.paths
        result.values.update(self.held)
        if is_round:
            # A round only seeds its stage: its steps and time count, not its records.
            for key in self.timing:
                self.timing[key] += float(result.timing_s.get(key, 0.0))
            self.n_steps += result.n_steps
            self.origin = self.origin[[result.best_start]]
            self.starts = np.asarray([[result.values[p] for p in paths]])
            return
        for key in self.timing:
            self.timing[key] += float(result.timing_s.get(key, 0.0))
        for entry in result.stages:
            entry = dict(entry, views=dict(stage_views))
            entry["origin"] = [int(self.origin[i]) for i in entry["origin"]]
            if not self.records and self.record is not None:
                entry["scan"] = self.record
            self.records.append(entry)
        self.n_steps += result.n_steps
        self.origin = self.origin[[result.best_start]]
        if self.stage_done is not None and (len(self.plan) > 1 or self.resume is not None):
            self.stage_done(
                StageDone(
                    number=len(self.records),
                    views=dict(stage_views),
                    loss=result.loss,
                    best_start=int(self.origin[0]),
                    values={p: result.values[p] for p in paths if p in self.interest},
                )
            )
        if k + 1 < len(self.plan):
            best = np.asarray([result.values[p] for p in paths])
            self.starts = branched_starts(self.space, best, self.branches[k])
            self.origin = np.repeat(self.origin, self.starts.shape[0])
        self.last = result

    def result(self) -> FitResult:
        """The last step's result with every step's records, starts and totals."""
        result, records = self.last, self.records
        paths = self.space.paths
        sub, template, views, options = self.current
        if self.plan[-1][1] == {} and _draws(options):
            _scatter_errors(result, sub, template, self.target, views, options)
        result.stages = records
        if self.resume is None:
            result.starts = [dict(zip(paths, map(float, row), strict=True)) for row in self.first]
        else:
            result.starts = self.resume.starts
        result.best_start = int(self.origin[0])
        if len(records) > 1:
            # fit() described only its own stage; say where its start came from.
            result.message = re.sub(
                r"\(best of \d+ starts: start \d+\)",
                f"(stage {len(records)} of {len(records)}; from the best of "
                f"{len(result.starts)} starts, start {result.best_start})",
                result.message,
            )
        result.n_steps = self.n_steps
        result.timing_s = self.timing
        return result


def branched_starts(
    space: ParameterSpace,
    best: Float[ArrayLike, " p"],
    branch: Sequence[tuple[str, Sequence[int]]],
) -> np.ndarray:
    """The starts a stage's `best` result (physical, order of `space.paths`) branches into.

    For each ``(path, offsets)`` of `branch` (several multiply), one start per offset with
    `path` at ``round(value) + offset``, moved inside its bounds by a small margin when it
    falls on or beyond one (so their number, and a vmapped fit's shapes, do not depend on
    the value). No branch: `best` alone. **Returns:** ``(n, p)``.
    """
    starts = np.asarray(best, dtype=float)[None, :]
    for path, offsets in branch:
        i = space.paths.index(path)
        lo, hi = float(space.all[i].lower), float(space.all[i].upper)
        margin = 1e-3 * (hi - lo) if math.isfinite(hi - lo) else 1e-3
        rows = []
        for row in starts:
            for offset in offsets:
                new = row.copy()
                new[i] = min(max(round(row[i]) + offset, lo + margin), hi - margin)
                rows.append(new)
        starts = np.asarray(rows)
    return starts


#: Rounds of a stage with draws: each measures the scatter between eyes at its start (the
#: previous round's result) and fits (see :mod:`invglare.fit.draw_scatter`).
DRAW_ROUNDS = 3


def _draws(options) -> int:
    """The most draws any view of `options` asks for (0: none)."""
    return max((int(o.get("draws", 0)) for o in (options or {}).values()), default=0)


def _with_scatter(space, template, target, views, view_options, starts):
    """A stage's view options, with the scatter between eyes measured at its first start for
    every statistics view that asks for `draws` (see :mod:`invglare.fit.draw_scatter`)."""
    options = _subset(view_options, views)
    if not _draws(options):
        return options
    fn = make_residual_fn(space, template, target, views, view_options=options)
    return scatter_options(fn, space.to_latent(jnp.asarray(starts[0])), options)


def _scatter_errors(result: FitResult, space, template, target, views, options) -> None:
    """Replace `result`'s covariance by the scatter between eyes with its parameters (and the
    noise), by :func:`~invglare.fit.draw_scatter.scatter_covariance`, and say so."""
    fn = make_residual_fn(space, template, target, views, view_options=options)
    values = jnp.asarray([result.values[p] for p in space.paths])
    latent = space.to_latent(values)
    cov_z = scatter_covariance(fn, latent, _draws(options), jacobian=result.latent_jacobian)
    d = np.asarray(space.jacobian_diag(latent), dtype=np.float64)
    cov = d[:, None] * cov_z * d[None, :]
    cols = [result.paths.index(p) for p in space.paths]
    full = np.full_like(np.asarray(result.covariance, dtype=np.float64), np.nan)
    full[np.ix_(cols, cols)] = cov
    result.covariance = full
    for p, var in zip(space.paths, np.diag(cov), strict=True):
        result.stderr[p] = float(np.sqrt(var)) if var >= 0 else math.nan
    result.covariance_scale = 1.0
    # The parameters' flags follow the new errors; the fit's own flags stay.
    bounds = {q.path: (q.lower, q.upper, q.init) for q in space.all}
    kept = [f for f in result.flags if "path" not in f or f["path"] not in space.paths]
    result.flags = kept + parameter_flags(
        space.paths, result.values, result.stderr, bounds, _subset(result.truth, space.paths)
    )
    # The message's flag summary (fit()'s, always last) is replaced by the new one.
    result.message = (
        re.sub(r"; \d+ flags?: .*$", "", result.message)
        + f"; standard errors from {_draws(options)} simulated eyes with these parameters "
        "(the scatter between draws and the noise)"
        + flags_summary(result.flags)
    )


def _numbered(progress, k: int, n_plan: int):
    """Report fit `k` of a plan's `n_plan` fits as stages of one run (fits before the last
    have one stage each; the last may have several, coarse to fine)."""
    if progress is None:
        return None
    return lambda p: progress(p._replace(stage=k + p.stage, n_stages=n_plan - 1 + p.n_stages))


def scan(
    space: ParameterSpace,
    forward: Forward,
    target: Float[ArrayLike, "h w"],
    views: Mapping[str, float],
    points: Float[ArrayLike, "m p"],
    *,
    n: int,
    fixed: Sequence[str] = (),
    view_options: Mapping[str, Mapping[str, Any]] | None = None,
    progress: Callable[[ScanProgress], None] | None = None,
) -> tuple[Float[np.ndarray, "k p"], dict[str, Any]]:
    """Score `points` by the loss of `views`; keep the best `n` as starts.

    No solving: one compiled loss, evaluated point by point (`fixed` paths held at the
    first point's values, as the stage the scan seeds holds them). When the flux is
    free, each point gets the flux that matches the photo's unclipped pixels (the
    photo's sum, the initial guess, misses what the clip cut off, which would swamp the
    comparison); the kept starts carry that flux.

    **Returns:** the kept starts ``(min(n, m), p)`` and a record of the scan (for the
    report): ``n_points``, ``views``, ``kept`` (indices), ``losses``, ``points`` (the
    parameters of interest of each point) and ``starts``.

    **Example:** ``starts, record = scan(space, forward, photo, {"radial": 1.0}, points, n=3)``.
    """
    points = np.array(points, dtype=np.float64)
    sub, template, free, _ = hold(space, forward, points, fixed)
    options = _subset(view_options, views)
    fn = make_residual_fn(sub, template, target, views, view_options=options)
    latent = np.asarray(sub.to_latent(free))
    flux = sub.paths.index("obs.flux") if "obs.flux" in sub.paths else None
    names = tuple(views)
    if progress is not None:
        progress(ScanProgress(0, len(latent), names))
    losses, fluxes = [], []
    with jax.enable_x64(True):
        for i, z in enumerate(latent):
            loss, f = _scan_point(fn, z, flux)
            losses.append(float(loss))
            fluxes.append(float(f))
            if progress is not None:
                progress(ScanProgress(i + 1, len(latent), names))
    losses = np.where(np.isfinite(losses), losses, np.inf)
    if flux is not None:
        col = space.paths.index("obs.flux")
        p = space.all[col]
        points[:, col] = np.clip(fluxes, p.lower + 1e-12 * abs(p.lower) + 1e-300, p.upper * 0.999)
    best = np.argsort(losses, kind="stable")[: min(n, len(points))]
    interest = [p.path for p in space.parameters]
    cols = [space.paths.index(p) for p in interest]
    return points[best], {
        "n_points": len(points),
        "views": dict(views),
        "kept": [int(i) for i in best],
        "losses": [float(v) for v in losses],
        "points": [dict(zip(interest, map(float, row[cols]), strict=True)) for row in points],
        "starts": points[best].tolist(),
    }


@eqx.filter_jit
def _scan_point(fn: ResidualFn, z, flux_index: int | None):
    """The loss at latent `z`, with the flux matched to the unclipped pixels if free."""
    if flux_index is None:
        return fn.loss(z), jnp.nan
    fwd = fn.forward_at(z)
    obs = fwd.obs
    unit = obs.response * obs.transform_psf(fwd.psf())  # counts per unit flux
    use = ~fn.saturated
    excess = jnp.sum(jnp.where(use, fn.target - obs.response * obs.background, 0.0))
    f = jnp.maximum(excess / jnp.sum(jnp.where(use, unit, 0.0)), 1e-30)
    p = fn.space.all[flux_index]
    z = z.at[flux_index].set(p.to_latent(f))
    return fn.loss(z), f


def hold(
    space: ParameterSpace,
    forward: Forward,
    starts: Float[ArrayLike, "n p"],
    fixed: Sequence[str],
) -> tuple[ParameterSpace, Forward, Float[np.ndarray, "n q"], dict[str, float]]:
    """The space without the `fixed` paths, a template holding them, and the reduced starts.

    The held values are those of the first start (a stage holds nuisances, which every
    start shares, or values that the previous stage's best result fixed).

    **Returns:** ``(space without them, forward with them written in, starts of the
    other parameters, {held path: value})``; everything unchanged when `fixed` is empty.

    **Example:** ``hold(space, forward, starts, ("obs.dx_px", "obs.dy_px"))``.
    """
    if not fixed:
        return space, forward, starts, {}
    starts = np.asarray(starts)
    keep = [i for i, p in enumerate(space.paths) if p not in fixed]
    held = {p: float(starts[0][i]) for i, p in enumerate(space.paths) if p in fixed}
    sub = ParameterSpace(
        [p for p in space.parameters if p.path not in fixed],
        [p for p in space.nuisance if p.path not in fixed],
    )
    return sub, space.apply(forward, starts[0]), starts[:, keep], held


def _subset(table, keys):
    """The entries of `table` whose keys are in `keys` (None when there are none)."""
    return None if table is None else {k: v for k, v in table.items() if k in keys} or None
