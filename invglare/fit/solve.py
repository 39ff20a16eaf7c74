"""Fitting: multi-start, coarse-to-fine optimistix solves and a covariance at the optimum.

:func:`fit` runs every start of a stage in **one** `jax.vmap`-ed, jitted call of
``optx.least_squares(..., throw=False)`` (Levenberg–Marquardt on the residual
vector, the default) or ``optx.minimise`` (BFGS on ``sum(r**2) / 2``). Under
`vmap` each start keeps its own damping and stops on its own criterion; the
batched loop simply runs until the slowest start is done, so a vmapped start
returns the same answer as a solo run (``batch="loop"`` does that, for checking
and for starts too memory-hungry to batch).

Coarse-to-fine: with ``coarse_to_fine=(2, 1)`` the first stage compares 2x2
block sums of target and prediction (flux-preserving; the read noise of a
block sum grows by 2; a block holding a clipped pixel is censored at its
observed sum) from all starts, and the second refines the best `refine_top` of
them at full resolution. The model is still evaluated at full resolution and
its prediction summed, so the parameters keep their units across stages; what
the coarse stage saves is the size of the least-squares problem, and what it
buys is an objective without pixel-scale structure. The image-statistic views
(radial, angular, halo) are reductions already and are evaluated at full
resolution in every stage. Blocks must stay smaller than the PSF core: on a
64-px photo with a 3-px Airy core, 4x4 blocks made the coarse objective *more*
multimodal (the starts settled in wrong minima) while 2x2 blocks did not.

**One likelihood.** The `pixels` view's residuals are the deviance residuals of the
photo's Poisson–Gaussian likelihood (:mod:`invglare.fit.deviance`), the one `invglare sample`
samples: half their sum of squares is ``-log L`` plus a constant of the data, so the final
fit is the maximum-likelihood fit. A final pixel view in a variance-stabilised domain
(``"anscombe"``, ``"pearson"``: biased) is solved first and then refined on the likelihood
from its best result (one more stage record, ``"likelihood": true``); the result's
`objective` says what was maximised. Such a first pass widens the basin from starts far
from the optimum: there the Gaussian likelihood punishes a model without light where the
photo has it by ``(o - e)**2 / V(e)``, far harder than the Anscombe domain's ``~4 g o``, and
its landscape is rugged (BFGS from 3 starts across a disk's bounds stopped at the lower
bound on the likelihood alone, at the truth after an Anscombe pass).

The covariance is the inverse of the *information* at the optimum, in latent space, mapped
to the physical values by the (diagonal) derivative of the transforms, ``C = D C_z D`` with
``D = diag(dx/dz)``: for the likelihood the Fisher information ``sum_i w_i grad(mu_i)
grad(mu_i)^T`` (``w`` the information of a pixel about its mean; a clipped pixel's survival
term enters by its Gauss–Newton curvature), for any other view its Gauss–Newton term
``J^T J``. It is multiplied by ``s**2`` (`covariance_scale`):

- ``"auto"`` (default): 1 when the objective is the likelihood alone (the information is
  the likelihood's), else the reduced chi-square;
- ``"chi2"``: the reduced chi-square ``sum(r**2) / (n - p)``, i.e. errors scaled by the
  actual scatter of the residuals (as ``scipy.optimize.curve_fit`` does by default): for
  views that are not noise-normalised (log, radial, angular) it puts the covariance in the
  residuals' own scale;
- ``"absolute"``: 1, trusting the noise model (noise-normalised residuals only);
- a number: that value.

**Flags.** A result carries the flags of :mod:`invglare.fit.trust` (a truth beyond 3
standard errors, a value at a bound, a reduced chi-square far from 1 with a likely cause, a
result not at the likelihood's optimum by a short local check of the exact likelihood).
"""

from __future__ import annotations

import collections
import dataclasses
import inspect
import itertools
import math
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from invglare.errors import ConfigError
from invglare.fit.observation import Forward
from invglare.fit.params import ParameterSpace
from invglare.fit.result import FitResult
from invglare.fit.trust import fit_flags, flags_summary, optimum_check
from invglare.fit.views import PixelView, ResidualFn, make_residual_fn

SOLVERS = ("lm", "bfgs")
COVARIANCE_SCALES = ("auto", "chi2", "absolute")
#: Leaves of the noise model the likelihood's deviance residuals cannot fit (their
#: saturated-model term depends on them; see :mod:`invglare.fit.deviance`).
NOISE_PATHS = ("obs.gain", "obs.read_noise")
BATCH_MODES = ("vmap", "loop")

# Status codes returned from inside the jitted solve (an optimistix RESULTS item can
# be compared but not carried out of `vmap` as a message).
_STATUS = (
    "successful",
    "nonlinear_max_steps_reached",
    "max_steps_reached",
    "nonfinite",
    "nonfinite_input",
    "nonlinear_divergence",
    "singular",
)


class FitProgress(NamedTuple):
    """One progress report: a start of a stage accepted a step with this loss."""

    stage: int
    n_stages: int
    factor: int
    start: int
    n_starts: int
    n_accepted: int
    loss: float


def _encode(x: Array) -> Array:
    """A float as uint32 words (two for float64), to reach a host callback bit for bit.

    JAX converts callback arguments with the callback thread's settings; where
    float64 is enabled by the thread-local ``jax.enable_x64()`` context, the
    callback thread would truncate a float64 loss to float32 (and warn on
    overflow). Integer words pass unchanged.
    """
    x = jnp.asarray(x)
    if x.dtype != jnp.float64:
        x = x.astype(jnp.float32)
    return jax.lax.bitcast_convert_type(x, jnp.uint32)


def _decode(words) -> float:
    w = np.asarray(words, dtype=np.uint32).reshape(-1)
    return float(w.view(np.float64)[0] if w.size == 2 else w.view(np.float32)[0])


# Host-side receivers of the per-step losses, by run id. The compiled solve carries only
# the id (an array), so one executable serves every fit of the same shape.
_SINKS: dict[int, Callable] = {}
_NEXT_RUN = itertools.count(1)


def _dispatch(run, start, loss_this, loss_last) -> None:
    sink = _SINKS.get(int(run))
    if sink is not None:
        sink(int(start), _decode(loss_this), _decode(loss_last))


class _Recorder(eqx.Module):
    """Optimistix `verbose` hook: sends each step's losses to the host, tagged with the start,
    for a live progress report.

    It is a Module so that `run` and `start` are array leaves — under `vmap` every
    start reports its own index (JAX runs a batched callback once per element). A program
    with a host callback is never loaded from JAX's persistent compilation cache (its key
    holds the callback's address), so only fits asked for progress carry one; the loss
    history comes from :class:`_LossLog` inside the program.
    """

    run: Array
    start: Array

    def __call__(self, **kwargs):
        this = kwargs.get("loss_this_step")
        last = kwargs.get("loss_last_accepted_step")
        if this is None or last is None:
            return
        jax.debug.callback(
            _dispatch,
            self.run.astype(jnp.int32),
            self.start.astype(jnp.int32),
            _encode(this[1]),
            _encode(last[1]),
        )


class _LossLog(eqx.Module):
    """A solver whose state also keeps the loss of the last accepted point at every step.

    The residual function returns its loss as optimistix's `aux`; a solver's `step`
    returns the aux of the last point it accepted before that step (at the first step,
    the start's), which is written into a `(max_steps,)` buffer. The history thus stays
    inside the compiled solve: no host callback, and under `vmap` a start that has
    stopped keeps its buffer as it was.
    """

    inner: Any
    size: int = eqx.field(static=True)

    @property
    def rtol(self):
        return self.inner.rtol

    @property
    def atol(self):
        return self.inner.atol

    @property
    def norm(self):
        return self.inner.norm

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        state = self.inner.init(fn, y, args, options, f_struct, aux_struct, tags)
        return state, jnp.full(self.size, jnp.nan, aux_struct.dtype), jnp.asarray(0)

    def step(self, fn, y, args, options, state, tags):
        inner, losses, k = state
        y, inner, aux = self.inner.step(fn, y, args, options, inner, tags)
        return y, (inner, losses.at[k].set(aux, mode="drop"), k + 1), aux

    def terminate(self, fn, y, args, options, state, tags):
        return self.inner.terminate(fn, y, args, options, state[0], tags)

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        y, aux, stats = self.inner.postprocess(fn, y, aux, args, options, state[0], tags, result)
        return y, aux, {**stats, "losses": state[1]}


class _LoggedLeastSquares(_LossLog, optx.AbstractLeastSquaresSolver):
    """:class:`_LossLog` of a least-squares solver (Levenberg–Marquardt)."""


class _LoggedMinimiser(_LossLog, optx.AbstractMinimiser):
    """:class:`_LossLog` of a minimiser (BFGS): `optx.minimise` accepts only these."""


@dataclasses.dataclass(frozen=True)
class _Config:
    solver: str
    rtol: float
    atol: float
    max_steps: int
    record: bool  # the loss history, in the program
    live: bool  # progress reports from host callbacks while the solve runs
    # The Jacobian at the solution, from the solver's last accepted step (LM only): the
    # covariance then needs no program of its own.
    keep_jacobian: bool = False


def _status_code(result) -> Array:
    code = jnp.asarray(-1)
    for i, name in enumerate(_STATUS):
        item = getattr(optx.RESULTS, name, None)
        if item is not None:
            code = jnp.where(result == item, i, code)
    return code


def jacobian_by_columns(fn: ResidualFn) -> Callable[[Array, Any], Array]:
    """`fn` whose forward-mode derivative is its dense Jacobian, made one column at a time.

    Optimistix's Levenberg–Marquardt (and `jax.jacfwd`) push all parameter directions
    through the model at once, as one batched tangent pass. XLA's CPU code for that
    batched pass is slow: the daylight-eye fit's Jacobian (4 parameters, 128² photo) took
    276 ms that way. Here the JVP builds the Jacobian with :func:`jacobian_columns` and
    returns ``J @ tangent``, so any batch of tangents afterwards is one small matrix
    product. Values and derivatives are those of `fn`; the extra cost is one column per
    parameter even when a single direction is asked for, which a solver that
    materialises the Jacobian pays anyway.
    """

    @jax.custom_jvp
    def residuals(latent: Array, args: Any) -> Array:
        return fn(latent, args)

    @residuals.defjvp
    def _jvp(primals, tangents):
        latent, args = primals
        jac, value = jacobian_columns(fn, latent, args)
        return value, jac @ tangents[0]

    return residuals


def jacobian_columns(fn: ResidualFn, latent: Array, args: Any = None) -> tuple[Array, Array]:
    """``(J, fn(latent, args))``: the dense Jacobian, one forward pass per column (unrolled).

    For a :class:`ResidualFn` column `i` is a JVP of :meth:`ResidualFn.at_parts` in the
    `i`-th latent value alone, so it costs only the part of the model that parameter
    reaches (daylight-eye fit: 57 ms for 4 columns, against 237 ms for a JVP of the whole
    vector per column). Any other `fn` is linearised once and its linear map evaluated
    on each unit vector. (Inside a `lax.map` loop the passes ran slower than unrolled.)
    """
    p = latent.shape[0]
    if isinstance(fn, ResidualFn):
        parts = [latent[i] for i in range(p)]
        columns = []
        for i in range(p):

            def along(z_i, i=i):
                return fn.at_parts([*parts[:i], z_i, *parts[i + 1 :]])

            # Every pass recomputes the same primal; XLA merges the copies (CSE).
            value, column = jax.jvp(along, (parts[i],), (jnp.ones_like(parts[i]),))
            columns.append(column)
    else:
        value, linear = jax.linearize(lambda z: fn(z, args), latent)
        columns = [linear(e) for e in jnp.eye(p, dtype=latent.dtype)]
    return jnp.stack(columns, axis=1), value


def _solve_one(fn: ResidualFn, y0: Array, start: Array, run: Array, cfg: _Config):
    """One start's solve: ``(value, loss, status code, steps, loss history, Jacobian)``; the
    history is the loss of the last accepted point at each step, `(max_steps,)` (NaN past
    the last step; empty unless `cfg.record`), the Jacobian the residuals' at `value`
    (``(0, p)`` unless `cfg.keep_jacobian`)."""
    verbose = _Recorder(run, start) if cfg.live else False
    if cfg.solver == "lm":
        residuals = jacobian_by_columns(fn)
        inner = optx.LevenbergMarquardt(rtol=cfg.rtol, atol=cfg.atol, verbose=verbose)
        logged = _LoggedLeastSquares

        def objective(y, args):
            r = residuals(y, args)
            return r, jnp.sum(r * r)

        solve = optx.least_squares
    else:
        inner = optx.BFGS(rtol=cfg.rtol, atol=cfg.atol, verbose=verbose)
        logged = _LoggedMinimiser

        def objective(y, args):
            r = fn(y, args)
            half = 0.5 * jnp.sum(r * r)
            return half, 2.0 * half

        solve = optx.minimise
    solver = logged(inner, cfg.max_steps) if cfg.record else inner
    sol = solve(objective, solver, y0, has_aux=True, max_steps=cfg.max_steps, throw=False)
    r = fn(sol.value, None)
    history = sol.stats["losses"] if cfg.record else jnp.zeros(0, r.dtype)
    jac = jnp.zeros((0, y0.shape[0]), r.dtype)
    if cfg.keep_jacobian:  # set for Levenberg–Marquardt only
        jac = _final_jacobian(sol.state[0] if cfg.record else sol.state)
    code, steps = _status_code(sol.result), sol.stats["num_steps"]
    return sol.value, jnp.sum(r * r), code, steps, history, jac


def _final_jacobian(state) -> Array:
    """The Jacobian at a Levenberg–Marquardt solve's result, ``(n, p)``.

    Optimistix keeps the linearisation of the last accepted point (which the solve returns)
    in its state; through :func:`jacobian_by_columns` that is ``t -> J @ t`` with `J`
    already computed, so materialising it is a product with the identity, not another pass
    of the model.
    """
    return state.f_info.jac.as_matrix()


def _status_message(code: int, n_steps: int, loss: float, cfg: _Config) -> tuple[bool, str]:
    name = _STATUS[code] if 0 <= code < len(_STATUS) else "unknown"
    if not math.isfinite(loss) or name in ("nonfinite", "nonfinite_input"):
        return False, (
            "non-finite values (NaN or inf) in the residuals or parameters: check the target "
            "for bad pixels, narrow the bounds, or start closer to a sensible model"
        )
    if name == "successful":
        return True, f"converged after {n_steps} steps"
    if name in ("nonlinear_max_steps_reached", "max_steps_reached"):
        return False, (
            f"hit max_steps={cfg.max_steps} without converging: raise max_steps or loosen "
            f"rtol={cfg.rtol:g} / atol={cfg.atol:g}"
        )
    if name == "nonlinear_divergence":
        return False, "the solver diverged: narrow the bounds or use other starts"
    if name == "singular":
        return False, (
            "a linear solve was singular: some parameter probably does not change the "
            "residuals (check its path and the chosen views)"
        )
    return False, "the solver stopped without converging (unrecognised optimistix result)"


class _LiveProgress:
    """Turns the per-step losses :class:`_Recorder` sends into :class:`FitProgress` reports,
    one whenever a start's last accepted loss changes."""

    def __init__(self, stage: int, n_stages: int, factor: int, n_starts: int, progress):
        self.info = (stage, n_stages, factor, n_starts)
        self.progress = progress
        self.accepted: dict[int, list[float]] = {}

    def __call__(self, i: int, loss_this: float, loss_last: float) -> None:
        seen = self.accepted.setdefault(i, [])
        # Optimistix reports sum(r**2) / 2, the fit's loss is sum(r**2). The first report
        # carries the start's loss as "this step" ("last accepted" is not yet defined); a
        # start that has stopped repeats its last one while the other starts go on (vmap).
        loss = 2.0 * (loss_last if seen else loss_this)
        if seen and loss == seen[-1]:
            return
        seen.append(loss)
        stage, n_stages, factor, n_starts = self.info
        self.progress(FitProgress(stage, n_stages, factor, i, n_starts, len(seen) - 1, loss))


def _loss_history(recorded: np.ndarray, n_steps: int, final: float) -> list[float]:
    """Loss at the start and after each accepted step, from a solve's recorded losses (the
    last accepted loss at each step) and its final loss, repeats dropped."""
    out: list[float] = []
    for v in [*np.asarray(recorded)[: int(n_steps)].tolist(), float(final)]:
        if not out or v != out[-1]:
            out.append(v)
    return out


#: Compiled solves kept for reuse: a fit with the same shapes, settings and parameter
#: space (bounds *and* initial values, which are part of the space's static identity)
#: skips compilation. Least recently used first.
_COMPILED: collections.OrderedDict = collections.OrderedDict()
_COMPILED_MAX = 8


def _batched(f, y, i, run, cfg):
    return jax.vmap(lambda yy, ii: _solve_one(f, yy, ii, run, cfg))(y, i)


def _batched_photos(f, y, i, run, cfg):
    # `f`, `y` and `run` carry a leading photo axis (arrays only); the start indices do not.
    one = lambda ff, yy, rr: _batched(ff, yy, i, rr, cfg)  # noqa: E731
    return eqx.filter_vmap(one, in_axes=(eqx.if_array(0), 0, 0))(f, y, run)


def _single_photos(f, y, i, run, cfg):
    one = lambda ff, yy, rr: _solve_one(ff, yy, i, rr, cfg)  # noqa: E731
    return eqx.filter_vmap(one, in_axes=(eqx.if_array(0), 0, 0))(f, y, run)


# `fn` is an argument, not a closure, so its arrays (target, fixed leaves) are inputs
# of the compiled program rather than baked-in constants. Keyed by batch mode; a "*"
# marks the modes that solve several photos at once (:func:`fit_many`).
_JITTED = {
    "vmap": eqx.filter_jit(_batched),
    "loop": eqx.filter_jit(_solve_one),
    "vmap*": eqx.filter_jit(_batched_photos),
    "loop*": eqx.filter_jit(_single_photos),
}


def _compile(fn, y0, starts, run, cfg, batch) -> tuple[Any, float]:
    """The compiled solve for these shapes and settings (cached) and the seconds compiling took."""
    dynamic, static = eqx.partition((fn, y0, starts), eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(dynamic)
    key = (batch, cfg, treedef, tuple((x.shape, x.dtype) for x in leaves), static)
    try:
        hit = _COMPILED.get(key)
    except TypeError:  # something unhashable in the model's static part: no caching
        key, hit = None, None
    if hit is not None:
        _COMPILED.move_to_end(key)
        return hit, 0.0
    t0 = time.perf_counter()
    compiled = _JITTED[batch].lower(fn, y0, starts, run, cfg).compile()
    elapsed = time.perf_counter() - t0
    if key is not None:
        _COMPILED[key] = compiled
        while len(_COMPILED) > _COMPILED_MAX:
            _COMPILED.popitem(last=False)
    return compiled, elapsed


def _run_stage(
    fn: ResidualFn,
    y0s: Float[Array, "n p"],
    cfg: _Config,
    batch: str,
    sink: Callable | None,
) -> tuple[np.ndarray, ...]:
    """Solve from every row of `y0s`; returns values, losses, codes, steps, recorded losses,
    final Jacobians (:func:`_solve_one`), compile s, solve s."""
    starts = jnp.arange(y0s.shape[0], dtype=jnp.int32)
    run_id = next(_NEXT_RUN)
    run = jnp.asarray(run_id, dtype=jnp.int32)
    if sink is not None:
        _SINKS[run_id] = sink
    try:
        if batch == "vmap":
            compiled, t_compile = _compile(fn, y0s, starts, run, cfg, batch)
            t1 = time.perf_counter()
            out = jax.block_until_ready(compiled(fn, y0s, starts, run, cfg))
            values, losses, codes, steps, histories, jacs = (np.asarray(o) for o in out)
        else:
            compiled, t_compile = _compile(fn, y0s[0], starts[0], run, cfg, batch)
            t1 = time.perf_counter()
            outs = [
                jax.block_until_ready(compiled(fn, y0s[k], starts[k], run, cfg))
                for k in range(y0s.shape[0])
            ]
            values, losses, codes, steps, histories, jacs = (
                np.stack([np.asarray(o[j]) for o in outs]) for j in range(6)
            )
        # Callbacks are asynchronous: make sure every report has arrived.
        jax.effects_barrier()
        t2 = time.perf_counter()
    finally:
        _SINKS.pop(run_id, None)
    return values, losses, codes, steps, histories, jacs, t_compile, t2 - t1


def _run_stage_many(
    fns: Sequence[ResidualFn],
    y0s: Sequence[Float[Array, "n p"]],
    cfg: _Config,
    batch: str,
    sinks: Sequence[Callable | None],
) -> list[tuple[np.ndarray, ...]]:
    """:func:`_run_stage` for several photos in one compiled call (vmapped over photos).

    Each photo's outputs come back as :func:`_run_stage` returns them; the compile and
    solve seconds, shared, are split evenly between the photos.
    """
    k = len(fns)
    fn = stack_modules(fns)
    y0 = jnp.stack([jnp.asarray(y) for y in y0s])
    starts = jnp.arange(y0.shape[1], dtype=jnp.int32)
    run_ids = [next(_NEXT_RUN) for _ in range(k)]
    runs = jnp.asarray(run_ids, dtype=jnp.int32)
    for run_id, sink in zip(run_ids, sinks, strict=True):
        if sink is not None:
            _SINKS[run_id] = sink
    try:
        if batch == "vmap":
            compiled, t_compile = _compile(fn, y0, starts, runs, cfg, "vmap*")
            t1 = time.perf_counter()
            out = jax.block_until_ready(compiled(fn, y0, starts, runs, cfg))
            values, losses, codes, steps, histories, jacs = (np.asarray(o) for o in out)
        else:
            compiled, t_compile = _compile(fn, y0[:, 0], starts[0], runs, cfg, "loop*")
            t1 = time.perf_counter()
            outs = [
                jax.block_until_ready(compiled(fn, y0[:, j], starts[j], runs, cfg))
                for j in range(y0.shape[1])
            ]
            values, losses, codes, steps, histories, jacs = (
                np.stack([np.asarray(o[m]) for o in outs], axis=1) for m in range(6)
            )
        jax.effects_barrier()
        t2 = time.perf_counter()
    finally:
        for run_id in run_ids:
            _SINKS.pop(run_id, None)
    t_c, t_s = t_compile / k, (t2 - t1) / k
    return [
        (values[j], losses[j], codes[j], steps[j], histories[j], jacs[j], t_c, t_s)
        for j in range(k)
    ]


def stack_modules(modules: Sequence[Any]) -> Any:
    """Pytrees of one structure as one, their arrays stacked along a new leading axis.

    **Raises:** :class:`~invglare.errors.ConfigError` when their static parts (shapes,
    static fields, non-array leaves) differ: such photos cannot share a compiled solve.
    """
    parts = [eqx.partition(m, eqx.is_array) for m in modules]
    leaves0, def0 = jax.tree_util.tree_flatten(parts[0][1])
    dyn_def = jax.tree_util.tree_structure(parts[0][0])
    shapes0 = [(x.shape, x.dtype) for x in jax.tree_util.tree_leaves(parts[0][0])]
    for i, (dyn, static) in enumerate(parts[1:], start=1):
        leaves, treedef = jax.tree_util.tree_flatten(static)
        shapes = [(x.shape, x.dtype) for x in jax.tree_util.tree_leaves(dyn)]
        same = treedef == def0 and jax.tree_util.tree_structure(dyn) == dyn_def
        same = same and shapes == shapes0 and _equal_leaves(leaves, leaves0)
        if not same:
            raise ConfigError(
                f"photo {i} of a vmapped group differs in structure from photo 0 (size, "
                "settings or static model fields): such photos are fitted apart"
            )
    stacked = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *(p[0] for p in parts))
    return eqx.combine(stacked, parts[0][1])


def _equal_leaves(a: list, b: list) -> bool:
    try:
        return len(a) == len(b) and all(bool(x == y) for x, y in zip(a, b, strict=True))
    except (TypeError, ValueError):
        return False


@eqx.filter_jit
def _jacobian_and_residuals(fn: ResidualFn, latent: Array) -> tuple[Array, Array]:
    # One compiled program; run eagerly, it would dispatch (and compile) op by op. A fit of
    # statistics (whose scoring form is itself) needs it not at all: its covariance and
    # the scatter covariance take the solve's own Jacobian (`_Config.keep_jacobian`), which
    # saved 62 s of compiling in the daylight other-draws fit.
    return jacobian_columns(fn, latent)


def _information(fn: ResidualFn, latent: Array) -> tuple[Array, Array]:
    """The scoring form's Jacobian and values: J^T J the information, J^T r the gradient."""
    return _jacobian_and_residuals(fn.information_form(), latent)


@eqx.filter_jit
def _predict(fn: ResidualFn, latent: Array) -> tuple[Array, Array, Array, Array]:
    residuals, ctx = fn.evaluate(latent)
    return ctx.expected, ctx.predicted, ctx.obs.variance(ctx.expected), residuals


def _covariance(
    fn: ResidualFn,
    latent: Array,
    space: ParameterSpace,
    scale: str | float,
    jacobian: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, float, int, float, str]:
    """Physical covariance, stderr, loss, effective residual count, s**2 and a note.

    `jacobian`: the scoring form's Jacobian at `latent` where the caller has it (a solve
    of residuals that are their own scoring form), else it is computed.
    """
    jac = _information(fn, latent)[0] if jacobian is None else jacobian
    jac = np.asarray(jac, dtype=np.float64)
    r = np.asarray(_predict(fn, latent)[3], dtype=np.float64)
    loss = float(r @ r)
    p = space.size
    # Masked pixels give residuals that are 0 whatever the parameters: not data.
    active = np.any(jac != 0, axis=1) | (r != 0)
    n = int(active.sum())
    dof = n - p
    if isinstance(scale, str):
        if scale == "auto" and fn.pure_likelihood:
            s2 = 1.0
        elif scale in ("chi2", "auto"):
            s2 = loss / dof if dof > 0 else math.nan
        elif scale == "absolute":
            s2 = 1.0
        else:
            raise ConfigError(
                f"covariance_scale {scale!r} is not 'auto', 'chi2', 'absolute' or a number"
            )
    else:
        s2 = float(scale)
    # A parameter whose Jacobian column is 0 is not constrained at all: its variance is
    # undefined (NaN), and the others come from the remaining block.
    free = np.any(jac != 0, axis=0)
    cov_z = np.full((p, p), np.nan)
    note = ""
    flat = [space.paths[k] for k in range(p) if not free[k]]
    if flat:
        note = f"; {', '.join(flat)} do not change the residuals (stderr undefined)"
    if free.any():
        jtj = jac[:, free].T @ jac[:, free]
        eig = np.linalg.eigvalsh(jtj)
        if np.all(np.isfinite(jtj)) and eig[-1] > 0 and eig[0] > 1e-12 * eig[-1]:
            cov_z[np.ix_(free, free)] = s2 * np.linalg.inv(jtj)
        else:
            note += (
                "; the covariance is singular (parameters are degenerate: some combination "
                "does not change the residuals), stderr undefined"
            )
    d = np.asarray(space.jacobian_diag(latent), dtype=np.float64)
    cov = d[:, None] * cov_z * d[None, :]
    stderr = np.sqrt(np.where(np.diag(cov) >= 0, np.diag(cov), np.nan))
    return cov, stderr, loss, n, s2, note


def _latent_starts(
    space: ParameterSpace,
    starts: Any,
    n_starts: int,
    key: PRNGKeyArray | None,
) -> Float[Array, "n p"]:
    if starts is None:
        key = jax.random.key(0) if key is None else key
        return space.sample_starts(key, n_starts)
    if isinstance(starts, Mapping):
        starts = [starts]
    if isinstance(starts, Sequence) and starts and isinstance(starts[0], Mapping):
        values = jnp.stack([space.values_from(s) for s in starts])
    else:
        values = jnp.atleast_2d(space.values_from(starts))
    for row in np.asarray(values):
        for p, v in zip(space.all, row, strict=True):
            ok = (p.lower < v < p.upper) if p.kind != "identity" else (p.lower <= v <= p.upper)
            if not ok:
                raise ConfigError(
                    f"start value {v:g} of {p.path!r} is not inside [{p.lower:g}, {p.upper:g}]"
                )
    return space.to_latent(values)


def fit(
    space: ParameterSpace,
    forward_template: Forward,
    target: Float[ArrayLike, "h w"],
    views: Mapping[str, float] | None = None,
    *,
    solver: str = "lm",
    n_starts: int = 3,
    key: PRNGKeyArray | None = None,
    starts: Any = None,
    max_steps: int = 256,
    rtol: float = 1e-6,
    atol: float = 1e-8,
    coarse_to_fine: Sequence[int] = (1,),
    refine_top: int = 1,
    view_options: Mapping[str, Mapping[str, Any]] | None = None,
    covariance_scale: str | float = "auto",
    truth: Mapping[str, float] | None = None,
    batch: str = "vmap",
    progress: Callable[[FitProgress], None] | None = None,
    record_history: bool = True,
    diagnostics: bool = True,
    final_likelihood: bool = True,
) -> FitResult:
    """Fit the free parameters of `space` to a target photo.

    **Arguments:**

    - `space`: free parameters and nuisances (paths into `forward_template`).
    - `forward_template`: ``Forward(model, obs)`` holding every fixed value.
    - `target`: the photo, linear counts, shape of the model's output.
    - `views`: ``{name: weight}`` (default ``{"pixels": 1.0}``: the photo's
      Poisson–Gaussian likelihood), see :mod:`invglare.fit.views`; `view_options` sets
      their options.
    - `solver`: ``"lm"`` (Levenberg–Marquardt on residuals) or ``"bfgs"`` (BFGS on
      ``sum(r**2) / 2``).
    - `n_starts`, `key`: starts drawn across the bounds by
      :meth:`ParameterSpace.sample_starts` (key defaults to ``jax.random.key(0)``);
      or `starts`: physical values, ``(n, p)`` or a list of ``{path: value}``.
    - `max_steps`, `rtol`, `atol`: solver budget and tolerances (on the latent
      step and the loss change, optimistix's Cauchy criterion).
    - `coarse_to_fine`: block sizes of the stages, ending with 1, e.g. ``(2, 1)``.
      Pick blocks no larger than about half the PSF core: coarser blocks wash out
      the core and make the objective *more* multimodal, not less.
    - `refine_top`: how many of a stage's best starts the next stage refines (1:
      only the best).
    - `covariance_scale`: ``"auto"``, ``"chi2"``, ``"absolute"`` or a number (module
      docstring).
    - `truth`: ``{path: value}`` stored in the result, for synthetic targets.
    - `batch`: ``"vmap"`` (all starts in one call) or ``"loop"`` (one call each).
    - `progress`: called with a :class:`FitProgress` whenever a start accepts a
      step (from JAX's host callback, while the solve runs; a solve with a callback is
      compiled anew in every process, never loaded from JAX's persistent cache).
    - `record_history`: keep each start's loss history in its stage records (recorded
      inside the compiled solve).
    - `diagnostics`: compute the covariance (the information at the optimum), the model
      and residual images, the flags and the optimum check. ``False`` skips them (stderr
      and covariance NaN, images None, no flags), which saves compiling more programs
      when the result only seeds a later fit.
    - `final_likelihood`: end on the likelihood: a pixel view in a variance-stabilised
      domain is refined on the likelihood from its best result (False: a seed stage,
      which may stay in that domain).

    Fitting in float64 (``jax.enable_x64``) is recommended: the tolerances above
    are near float32's resolution.

    **Returns:** a :class:`~invglare.fit.FitResult`.

    **Example:**

    ```python
    res = fit(space, Forward(model, obs), photo, {"pixels": 1.0}, n_starts=3,
              coarse_to_fine=(4, 1), key=jax.random.key(1))
    print(res.summary())
    ```
    """
    run = _FitRun(
        space, forward_template, target, views, solver=solver, n_starts=n_starts, key=key,
        starts=starts, max_steps=max_steps, rtol=rtol, atol=atol, coarse_to_fine=coarse_to_fine,
        refine_top=refine_top, view_options=view_options, covariance_scale=covariance_scale,
        truth=truth, batch=batch, progress=progress, record_history=record_history,
        diagnostics=diagnostics, final_likelihood=final_likelihood,
    )  # fmt: skip
    for s in range(run.n_stages):
        fn, y0s, sink = run.stage_inputs(s)
        run.stage_done(s, *_run_stage(fn, y0s, run.cfg, batch, sink))
    return run.result()


def fit_many(
    spaces: Sequence[ParameterSpace],
    forward_templates: Sequence[Forward],
    targets: Sequence[Float[ArrayLike, "h w"]],
    views: Mapping[str, float] | None = None,
    *,
    starts: Sequence[Any],
    truths: Sequence[Mapping[str, float] | None] | None = None,
    progress: Sequence[Callable[[FitProgress], None] | None] | None = None,
    view_options: Mapping[str, Mapping[str, Any]]
    | Sequence[Mapping[str, Mapping[str, Any]] | None]
    | None = None,
    batch: str = "vmap",
    **settings: Any,
) -> list[FitResult]:
    """Fit several photos of one structure with one compiled solve per stage (`jax.vmap`).

    The photos share their parameter paths and bounds, views and settings, and their
    residual functions their static structure (photos of one size fitted with one config
    do); each keeps its own starts, guesses and truth. Each result is what :func:`fit`
    returns for that photo alone, up to the rounding of a batched computation: under
    `vmap` every photo stops on its own criterion, while the batched loop runs until the
    slowest photo is done.

    **Arguments:** one entry per photo in `spaces`, `forward_templates`, `targets`,
    `starts` (physical, ``(n, p)``; the same `n` for every photo), `truths` and
    `progress`; `view_options` one mapping shared by all or one per photo (a statistics
    view's measured scatter between eyes differs by photo); `views`, `batch` and `settings`
    (the other keyword arguments of :func:`fit`) are shared.

    **Returns:** one :class:`~invglare.fit.FitResult` per photo, in order.

    **Raises:** :class:`~invglare.errors.ConfigError` for lists of different lengths, no
    photo, or photos whose residual functions differ in structure.

    **Example:** ``fit_many([space] * 2, [fwd_a, fwd_b], [photo_a, photo_b], starts=[s, s])``.
    """
    k = len(targets)
    truths = [None] * k if truths is None else list(truths)
    progress = [None] * k if progress is None else list(progress)
    if view_options is None or isinstance(view_options, Mapping):
        view_options = [view_options] * k
    options = list(view_options)
    lengths = {
        len(spaces), len(forward_templates), len(starts), len(truths), len(progress), len(options)
    }  # fmt: skip
    if k == 0 or lengths != {k}:
        raise ConfigError(
            "fit_many needs one space, forward template, target, set of starts, truth, "
            "progress and view options per photo, at least one; got "
            f"{len(spaces)}, {len(forward_templates)}, {k}, {len(starts)}, {len(truths)}, "
            f"{len(progress)}, {len(options)}"
        )
    given = ("starts", "n_starts", "truth", "progress", "view_options", "batch")
    settings = _fit_defaults(but=given) | settings
    runs = [
        _FitRun(sp, fw, tg, views, starts=st, n_starts=np.shape(st)[0], truth=tr, progress=pr,
                view_options=vo, batch=batch, **settings)
        for sp, fw, tg, st, tr, pr, vo in zip(spaces, forward_templates, targets, starts,
                                              truths, progress, options, strict=True)
    ]  # fmt: skip
    for s in range(runs[0].n_stages):
        inputs = [run.stage_inputs(s) for run in runs]
        outs = _run_stage_many(
            [i[0] for i in inputs], [i[1] for i in inputs], runs[0].cfg, batch,
            [i[2] for i in inputs],
        )  # fmt: skip
        for run, out in zip(runs, outs, strict=True):
            run.stage_done(s, *out)
    return [run.result() for run in runs]


def _fit_defaults(but: Collection[str]) -> dict[str, Any]:
    """:func:`fit`'s keyword defaults less those named: fit_many's settings fall back to them,
    so that they live in fit's signature alone."""
    params = inspect.signature(fit).parameters.values()
    return {p.name: p.default for p in params if p.kind is p.KEYWORD_ONLY and p.name not in but}


class _FitRun:
    """One photo's fit, stage by stage (coarse to fine): :func:`fit` and :func:`fit_many`
    run the solves, one photo at a time or several in one call, and this keeps the books.
    It takes every keyword argument of :func:`fit`, whose signature holds their defaults."""

    def __init__(
        self,
        space: ParameterSpace,
        forward_template: Forward,
        target: Float[ArrayLike, "h w"],
        views: Mapping[str, float] | None,
        *,
        solver: str,
        n_starts: int,
        key: PRNGKeyArray | None,
        starts: Any,
        max_steps: int,
        rtol: float,
        atol: float,
        coarse_to_fine: Sequence[int],
        refine_top: int,
        view_options: Mapping[str, Mapping[str, Any]] | None,
        covariance_scale: str | float,
        truth: Mapping[str, float] | None,
        batch: str,
        progress: Callable[[FitProgress], None] | None,
        record_history: bool,
        diagnostics: bool,
        final_likelihood: bool,
    ):
        if solver not in SOLVERS:
            raise ConfigError(f"solver {solver!r} is not one of {', '.join(SOLVERS)}")
        if batch not in BATCH_MODES:
            raise ConfigError(f"batch {batch!r} is not one of {', '.join(BATCH_MODES)}")
        factors = tuple(coarse_to_fine)
        if (
            not factors
            or any(not isinstance(f, int | np.integer) or f < 1 for f in factors)
            or factors[-1] != 1
        ):
            raise ConfigError(
                "coarse_to_fine must be integers >= 1 ending with 1, e.g. (4, 1); got "
                f"{factors!r}"
            )
        if int(refine_top) != refine_top or refine_top < 1:
            raise ConfigError(f"refine_top must be an integer >= 1, got {refine_top!r}")
        if int(max_steps) != max_steps or max_steps < 1:
            raise ConfigError(f"max_steps must be an integer >= 1, got {max_steps!r}")
        if not (rtol >= 0 and atol >= 0 and rtol + atol > 0):
            raise ConfigError(
                f"rtol and atol must be >= 0 and not both 0, got {rtol!r}, {atol!r}"
            )
        if isinstance(covariance_scale, str) and covariance_scale not in COVARIANCE_SCALES:
            raise ConfigError(
                f"covariance_scale {covariance_scale!r} is not one of "
                f"{', '.join(COVARIANCE_SCALES)} or a number"
            )
        views = {"pixels": 1.0} if views is None else views
        if truth is not None:
            unknown = [p for p in truth if p not in space.paths]
            if unknown:
                raise ConfigError(f"truth names {unknown} which are not free parameters")

        self.t_start = time.perf_counter()
        self.space, self.views, self.truth = space, views, truth
        self.refine_top = int(refine_top)
        self.covariance_scale, self.diagnostics = covariance_scale, diagnostics
        self.progress = progress
        self.solver = solver
        self.cfg = _Config(
            solver, float(rtol), float(atol), int(max_steps), bool(record_history),
            live=progress is not None,
        )  # fmt: skip
        self.fn_full = fn_full = make_residual_fn(
            space, forward_template, target, views, view_options=view_options
        )
        self.first_pass = fn_full.stabilised_views() if final_likelihood else ()
        self.fn_final = fn_final = fn_full.with_likelihood() if self.first_pass else fn_full
        if final_likelihood and _has_likelihood(fn_final):
            noise = [p for p in space.paths if p in NOISE_PATHS]
            if noise:
                raise ConfigError(
                    f"{', '.join(noise)} cannot be fitted by the pixel likelihood's least "
                    "squares (its deviance residuals' constant depends on them): measure gain "
                    "and read noise from flat and dark frames and fix them, or sample them "
                    "with `invglare sample`, whose posterior is the likelihood itself"
                )
        if solver == "lm" and fn_final.scores_itself:
            # Its covariance is then the solve's own Jacobian (see `_Config`). Not tied to
            # `diagnostics`: a seed round and the final fit still share one program.
            self.cfg = dataclasses.replace(self.cfg, keep_jacobian=True)
        # (factor, residuals) of each stage; a first pass in a stabilised domain ends on the
        # likelihood, from the best result, at full resolution.
        self.plan = [(int(f), fn_full if f == 1 else fn_full.with_factor(int(f))) for f in factors]
        if self.first_pass:
            self.plan.append((1, fn_final))
        y0s = _latent_starts(space, starts, n_starts, key)
        self.first_starts = [space.as_dict(v) for v in np.asarray(space.from_latent(y0s))]
        self.stages: list[dict[str, Any]] = []
        self.compile_s = self.solve_s = 0.0
        self.stage_y0 = y0s
        self.origin = np.arange(y0s.shape[0])  # first-stage start each start descends from
        self.steps_so_far = np.zeros(y0s.shape[0], dtype=int)

    @property
    def n_stages(self) -> int:
        return len(self.plan)

    def stage_inputs(self, s: int) -> tuple[ResidualFn, Array, Callable | None]:
        """Stage `s`'s residual function, latent starts and receiver of live step losses."""
        factor, fn = self.plan[s]
        n = self.stage_y0.shape[0]
        live = None if self.progress is None else _LiveProgress(
            s, len(self.plan), factor, n, self.progress)  # fmt: skip
        return fn, self.stage_y0, live

    def stage_done(self, s, values, losses, codes, steps, recorded, jacobians, t_c, t_s) -> None:
        """Book stage `s`'s solves; pick the starts of the next stage."""
        self.compile_s += t_c
        self.solve_s += t_s
        losses = np.where(np.isfinite(losses), losses, np.inf)
        statuses = [
            _status_message(int(c), int(n), float(lo), self.cfg)
            for c, n, lo in zip(codes, steps, losses, strict=True)
        ]
        order = np.argsort(losses, kind="stable")
        factor, fn = self.plan[s]
        record = {
            "factor": factor,
            "origin": [int(o) for o in self.origin],
            "n_steps": [int(n) for n in steps],
            "final_loss": [float(v) for v in losses],
            "converged": [c for c, _ in statuses],
            "messages": [m for _, m in statuses],
            "loss_history": [
                _loss_history(recorded[i], steps[i], losses[i])
                if self.cfg.record
                else [float(losses[i])]
                for i in range(self.stage_y0.shape[0])
            ],
            "best": int(order[0]),
            "compile_s": t_c,
            "solve_s": t_s,
        }
        if self.first_pass:
            record["likelihood"] = fn is self.fn_final
        self.stages.append(record)
        self.steps_so_far = self.steps_so_far + steps.astype(int)
        self.last = (values, order, statuses, jacobians)
        if s + 1 < len(self.plan):
            # The next, finer stage starts from the best few of this one; the likelihood's
            # refinement after a first pass from the best one.
            final_next = self.first_pass and self.plan[s + 1][1] is self.fn_final
            top = 1 if final_next else self.refine_top
            keep = order[: max(1, min(top, len(order)))]
            self.stage_y0 = jnp.asarray(values[keep])
            self.origin, self.steps_so_far = self.origin[keep], self.steps_so_far[keep]

    def result(self) -> FitResult:
        """The result after the last stage: the best start, its covariance, images and flags."""
        values, order, statuses, jacobians = self.last
        space, fn_full, fn_final, stages = self.space, self.fn_full, self.fn_final, self.stages
        truth = self.truth
        k = int(order[0])
        best_latent = jnp.asarray(values[k])
        jacobian = jacobians[k] if self.cfg.keep_jacobian else None
        best_start = int(self.origin[k])
        n_steps_total = int(self.steps_so_far[k])
        converged, message = statuses[k]

        values = space.as_dict(space.from_latent(best_latent))
        objective = fn_final.objective()
        if self.first_pass:
            domains = sorted({v.domain for v in fn_full.views if isinstance(v, PixelView)} - {
                "likelihood", "log"})  # fmt: skip
            objective += f", refined from a first pass in the {'/'.join(domains)} domain"
        p = space.size
        flags: list[dict[str, Any]] = []
        optimum = None
        if self.diagnostics:
            cov, stderr, loss, n_res, s2, note = _covariance(
                fn_final, best_latent, space, self.covariance_scale, jacobian
            )
            expected, predicted, variance, _ = (
                np.asarray(a) for a in _predict(fn_final, best_latent)
            )  # fmt: skip
            target_arr = np.asarray(fn_final.target)
            sigma = np.sqrt(variance + 1e-30)
            saturated = np.asarray(fn_final.saturated)
            residual_map = np.where(saturated, 0.0, (target_arr - expected) / sigma)
            # A fit of another eye's statistics is not at the pixel likelihood of the
            # model's own draw, nor should it be.
            optimum = (
                None if fn_final.draw_whitened else _check_optimum(fn_final, best_latent, space)
            )
            reduced = loss / (n_res - p) if n_res > p else math.nan
            obs = fn_final.forward.obs
            flags = fit_flags(
                paths=list(space.paths),
                values=values,
                stderr={path: float(e) for path, e in zip(space.paths, stderr, strict=True)},
                bounds={q.path: (q.lower, q.upper, q.init) for q in space.all},
                truth=truth,
                reduced_chi2=reduced,
                dof=n_res - p,
                normalised=_noise_normalised(fn_final),
                optimum=optimum,
                likelihood_pure=fn_final.pure_likelihood,
                residual_map=residual_map,
                expected=expected,
                used=~saturated,
                gain=float(obs.gain),
                read_noise=float(obs.read_noise),
            )
        else:
            cov, stderr = np.full((p, p), np.nan), np.full(p, np.nan)
            loss = float(stages[-1]["final_loss"][k])
            shape = tuple(fn_final.target.shape)
            n_res, s2, note = sum(v.size(shape) for v in fn_final.views), math.nan, ""
            residual_map = predicted = None
        n_starts_run = len(stages[0]["n_steps"])
        n_plan = len(self.plan)
        where = f"stage {n_plan}/{n_plan} at full resolution" if n_plan > 1 else ""
        summary = (
            f"{message} ({'best of ' + str(n_starts_run) + ' starts: start ' + str(best_start)}"
            f"{'; ' + where if where else ''}){note}"
        )
        reduced = loss / (n_res - p) if n_res > p else math.nan
        summary += flags_summary(flags)
        return FitResult(
            paths=list(space.paths),
            values=values,
            stderr={path: float(e) for path, e in zip(space.paths, stderr, strict=True)},
            covariance=cov,
            nuisance=[pp.path for pp in space.nuisance],
            truth={k: float(v) for k, v in truth.items()} if truth else None,
            loss=loss,
            reduced_chi2=reduced,
            n_residuals=n_res,
            covariance_scale=s2,
            converged=bool(converged),
            message=summary,
            n_steps=n_steps_total,
            best_start=best_start,
            timing_s={
                "compile": self.compile_s,
                "solve": self.solve_s,
                "total": time.perf_counter() - self.t_start,
            },
            solver=self.solver,
            views={k: float(v) for k, v in self.views.items()},
            stages=stages,
            starts=self.first_starts,
            residual_map=residual_map,
            model_image=predicted,
            objective=objective,
            flags=flags,
            optimum_check=None if optimum is None else _plain_check(optimum),
            latent_jacobian=jacobian,
        )


def _plain_check(optimum: dict) -> dict:
    """The optimum check's numbers for the result (the latent point left out)."""
    return {k: v for k, v in optimum.items() if k != "latent"}


def _has_likelihood(fn: ResidualFn) -> bool:
    return any(isinstance(v, PixelView) and v.likelihood for v in fn.views)


def _noise_normalised(fn: ResidualFn) -> bool:
    """Whether the loss is a chi-square: every view a noise-normalised pixel view, weight 1."""
    return all(
        isinstance(v, PixelView) and v.domain in ("likelihood", "anscombe", "pearson") and w == 1
        for v, w in zip(fn.views, fn.weights, strict=True)
    )


def _check_optimum(fn: ResidualFn, latent: Array, space: ParameterSpace) -> dict | None:
    """:func:`invglare.fit.trust.optimum_check` on the photo's likelihood alone, reusing the
    fit's compiled programs when its objective was that likelihood. None when the photo's
    likelihood is undefined (no read noise and dark pixels)."""
    if not fn.pure_likelihood:
        try:
            fn = fn.likelihood_only()
        except ConfigError:
            return None

    def information(z):
        return _information(fn, jnp.asarray(z, dtype=latent.dtype))

    def deviance(z):
        r = np.asarray(_predict(fn, jnp.asarray(z, dtype=latent.dtype))[3], dtype=np.float64)
        return float(r @ r)

    def inside(z):
        x = np.asarray(space.from_latent(jnp.asarray(z, dtype=latent.dtype)))
        return all(q.lower <= v <= q.upper for q, v in zip(space.all, x, strict=True))

    return optimum_check(information, deviance, np.asarray(latent), inside)
