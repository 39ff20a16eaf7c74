"""The tables of a fit config that say what is fitted and how (schema: :mod:`invglare.config.fit`).

- ``[[free]]``: the free parameters (:func:`read_free`), each named by its parameter
  path (:mod:`invglare.config.paths`);
- ``[[discrete]]``: static integer choices tried value by value (:func:`read_discrete`);
- ``[views]`` and ``[view_options]``: what the residuals compare (:func:`read_views`,
  :func:`read_view_options`);
- ``[[stage]]``: stages run before the final fit (:func:`read_stages`);
- ``[solver]``: the solver's settings and the starts (:func:`read_solver`).

Each reader checks its table completely (unknown keys, types, ranges, paths that do not
exist) and raises :class:`~invglare.errors.ConfigError` naming the table and key.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Mapping
from typing import Any

from invglare.config.paths import config_key_to_path, get_key, path_to_config_key
from invglare.config.section import Section
from invglare.errors import ConfigError

FREE_KEYS = ("path", "lower", "upper", "init", "prior", "transform", "nuisance", "indices")
DISCRETE_KEYS = ("path", "values", "key")
STAGE_KEYS = ("views", "max_steps", "fixed", "branch")

#: Old ``[[discrete]]`` keys already warned about (once per spelling).
_WARNED: set[str] = set()
_KEY_HINT = (
    "; a [[discrete]] key is a dotted key of the model config, e.g. "
    "'model.camera.diaphragm.n_blades' or 'model.shapes.0.n_blades' (better: name the "
    "choice by its parameter path, path = 'model.aperture.diaphragm.n_blades')"
)


@dataclasses.dataclass(frozen=True)
class DiscreteOption:
    """A static (integer) choice of the model tried value by value.

    `path` names it in the one path language (``"model.aperture.diaphragm.n_blades"``),
    `key` is the same value's dotted key in the model config, which each candidate is
    written into before the model is rebuilt (``"model.camera.diaphragm.n_blades"``);
    `values` are the candidates, `truth` the value in the ground truth (None if unknown).
    """

    path: str
    key: str
    values: tuple[int, ...]
    truth: int | None = None


def number(value: Any, where: str, allow_inf: bool = False) -> float:
    """`value` as a float; a bool, a non-number, NaN (and inf unless `allow_inf`) are refused."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(f"{where} must be a number, got {value!r}")
    v = float(value)
    if math.isnan(v) or (not allow_inf and math.isinf(v)):
        raise ConfigError(f"{where} must be a finite number, got {value!r}")
    return v


def read_free(
    tables: Any, forward: Any, guesses: Mapping[str, float]
) -> tuple[list, list, dict[int, tuple[float, float]]]:
    """Parameters and nuisances of the ``[[free]]`` tables, and the init ranges by index.

    Paths are checked against `forward` (the error lists the valid ones) and kept in the
    one path language (an older spelling is rewritten, with a DeprecationWarning).
    Parameters of interest come first, nuisances after (``obs.*`` by default).
    Initial values the table leaves out come from `guesses` or the model
    (:func:`invglare.fit.starts.default_init`).
    """
    from invglare.fit.params import Parameter
    from invglare.fit.paths import spelling, vector_length
    from invglare.fit.starts import default_init

    if not isinstance(tables, list) or not tables:
        raise ConfigError(
            "the fit has no free parameters; add [[free]] tables with path, lower, upper"
        )
    ranges: dict[int, tuple[float, float]] = {}
    entries = []
    for i, table in enumerate(tables):
        where = f"free[{i}]"
        if not isinstance(table, dict):
            raise ConfigError(f"[[free]] entry {i} must be a table, got {table!r}")
        for key in table:
            if key not in FREE_KEYS:
                raise ConfigError(
                    f"{where}: unknown key {key!r}; valid keys: {', '.join(FREE_KEYS)}"
                )
        sec = Section(table, where)
        path = sec.get("path", str, required=True)
        where = f"free[{i}] ({path})"
        indices = sec.get("indices", list, None)
        # A whole vector leaf (a lash layout's angle_deg) frees its elements, each with the
        # table's bounds; `indices` picks some. Check the path first: its error lists the
        # valid paths.
        length = vector_length(forward, path)
        if length is None and indices is not None:
            raise ConfigError(f"{where}: indices are for a vector leaf; {path!r} is a scalar")
        if length is not None:
            indices = list(range(length)) if indices is None else indices
            if not indices or any(
                isinstance(j, bool) or not isinstance(j, int) or not 0 <= j < length
                for j in indices
            ):
                raise ConfigError(
                    f"{where}.indices must be a non-empty list of integers in [0, {length}), "
                    f"got {indices!r}"
                )
            paths = [spelling(forward, f"{path}[{j}]") for j in indices]
        else:
            paths = [spelling(forward, path)]
        lower = number(sec.get("lower", (int, float), required=True), f"{where}.lower", True)
        upper = number(sec.get("upper", (int, float), required=True), f"{where}.upper", True)
        init_raw = sec.get("init", (int, float, list), None)
        prior = sec.get("prior", (str, list, dict), None)
        transform = sec.get("transform", str, "auto")
        is_nuisance = sec.get("nuisance", bool, paths[0].startswith("obs."))
        init_range = None
        if isinstance(init_raw, list):
            if len(init_raw) != 2:
                raise ConfigError(
                    f"{where}.init must be a number or a range [low, high], got {init_raw!r}"
                )
            lo, hi = (number(v, f"{where}.init") for v in init_raw)
            if not (lower <= lo < hi <= upper):
                raise ConfigError(
                    f"{where}: the init range [{lo:g}, {hi:g}] must be increasing and lie "
                    f"inside the bounds [{lower:g}, {upper:g}]"
                )
            init_range = (lo, hi)
        for element in paths:
            if init_range is not None:
                init = 0.5 * (init_range[0] + init_range[1])
                ranges[len(entries)] = init_range
            elif init_raw is not None:
                init = number(init_raw, f"{where}.init")
            else:
                init = default_init(forward, element, lower, upper, guesses)
            try:
                param = Parameter(
                    element, lower, upper, init=init, prior=prior, transform=transform
                )
            except TypeError as err:  # a prior table with unknown keys
                raise ConfigError(
                    f"{where}.prior must be 'uniform', [kind, mean, std] or a table with kind, "
                    f"mean, std; got {prior!r} ({err})"
                ) from None
            entries.append((param, is_nuisance))
    # Parameters of interest first (their starts are spread), nuisances after; the init
    # ranges follow their parameter to its new index.
    order = [k for k, (_, n) in enumerate(entries) if not n] + [
        k for k, (_, n) in enumerate(entries) if n
    ]
    params, nuisance, moved = [], [], {}
    for new, old in enumerate(order):
        param, is_nuisance = entries[old]
        (nuisance if is_nuisance else params).append(param)
        if old in ranges:
            moved[new] = ranges[old]
    return params, nuisance, moved


def read_discrete(tables: Any, model_config: Mapping[str, Any], forward: Any) -> list:
    """The :class:`DiscreteOption` s of the ``[[discrete]]`` tables.

    Each names its choice by ``path``, the parameter path of an integer choice of the
    built model (`forward`, e.g. ``"model.aperture.diaphragm.n_blades"``). The older
    ``key`` (a dotted key of the model config) still works, with a DeprecationWarning
    naming the path that replaces it (once per key).
    """
    from invglare.fit.paths import static_int

    if tables is None:
        return []
    if not isinstance(tables, list):
        raise ConfigError(f"[[discrete]] must be a list of tables, got {tables!r}")
    kind = model_config.get("model", {}).get("kind", "")
    out = []
    for i, table in enumerate(tables):
        where = f"discrete[{i}]"
        sec = Section(table, where)
        path = sec.get("path", str, None)
        key = sec.get("key", str, None)
        values = sec.get("values", list, required=True)
        sec.finish()
        if (path is None) == (key is None):
            raise ConfigError(
                f"{where} needs a path, the parameter path of an integer choice of the model "
                "(e.g. path = 'model.aperture.diaphragm.n_blades'), and not also a key"
            )
        if path is None:
            path = _path_of_key(kind, key, forward, where)
            current = get_key(model_config, key, where, _KEY_HINT)
            if isinstance(current, bool) or not isinstance(current, int):
                raise ConfigError(
                    f"{where}: the model config's {key!r} is {current!r}, not an integer; "
                    "continuous values are fitted as [[free]] parameters"
                )
        else:
            static_int(forward, path)  # the error lists the model's integer choices
            key = path_to_config_key(kind, path)
            # Each candidate is written into the key's table: it must be there (the key
            # itself may be left to its default).
            table, _, _ = key.rpartition(".")
            if table:
                get_key(model_config, table, f"{where} ({path})")
        if not values or not all(isinstance(v, int) and not isinstance(v, bool) for v in values):
            raise ConfigError(f"{where}.values must be a non-empty list of integers, got {values}")
        if len(set(values)) != len(values):
            raise ConfigError(f"{where}.values lists a value twice: {values}")
        out.append(DiscreteOption(path, key, tuple(values)))
    return out


def _path_of_key(kind: str, key: str, forward: Any, where: str) -> str:
    """The parameter path that replaces an older ``[[discrete]]`` model-config `key`.

    A key whose value the built model holds under no path (a raster size the model
    turns into its grid) keeps its key as its name: there is nothing to rename it to.
    """
    from invglare.fit.paths import static_int

    path = config_key_to_path(kind, key)
    try:
        static_int(forward, path)
    except ConfigError:
        return key
    if key not in _WARNED:
        _WARNED.add(key)
        warnings.warn(
            f"{where}: key = {key!r} (a model-config key) is deprecated; name the choice by "
            f"its parameter path, as [[free]] does: path = {path!r}",
            DeprecationWarning,
            stacklevel=3,
        )
    return path


def read_views(table: Any, where: str) -> dict[str, float]:
    """``{view: weight}`` of a ``[views]`` (or a stage's ``views``) table."""
    from invglare.fit.views import VIEWS

    if not isinstance(table, dict) or not table:
        raise ConfigError(f"{where} must be a table of name = weight, e.g. pixels = 1.0")
    views = {}
    for view, weight in table.items():
        if view not in VIEWS:
            raise ConfigError(
                f"{where} names unknown view {view!r}; valid views: {', '.join(VIEWS)}"
            )
        w = number(weight, f"{where} {view}")
        if w < 0:
            raise ConfigError(f"{where} weight of {view!r} must be >= 0, got {w:g}")
        views[view] = w
    return views


def read_view_options(
    options: Any, used: set[str], shape: tuple[int, ...], guess: Any, target: Any
) -> dict[str, dict[str, Any]]:
    """The ``[view_options]`` tables, each for a view some stage `used`; every option is
    checked by building the view on the photo (`shape`, the observation `guess`, `target`),
    so an unknown option fails before any model is evaluated."""
    from invglare.fit.views import build_view

    if not isinstance(options, dict):
        raise ConfigError(f"[view_options] must hold one table per view, got {options!r}")
    for view, opts in options.items():
        if view not in used:
            raise ConfigError(
                f"[view_options.{view}] is for a view no stage uses ({', '.join(sorted(used))})"
            )
        if not isinstance(opts, dict):
            raise ConfigError(f"[view_options.{view}] must be a table, got {opts!r}")
    for view in used:
        build_view(view, options.get(view), shape, guess, target)
    return {k: dict(v) for k, v in options.items()}


def _free_path(forward: Any, paths: tuple[str, ...], path: Any, where: str) -> str:
    """`path` in the one path language, refused unless it is a free parameter (`paths`)."""
    from invglare.fit.paths import spelling

    try:
        path = spelling(forward, path)
    except ConfigError:
        pass  # refused below, naming the free parameters
    if path not in paths:
        raise ConfigError(
            f"{where} names {path!r}, which is not a free parameter ({', '.join(paths)})"
        )
    return path


def read_stages(tables: Any, default_steps: int, forward: Any, paths: tuple[str, ...]) -> tuple:
    """The :class:`~invglare.fit.stages.Stage` s of the ``[[stage]]`` tables; their
    ``fixed`` and ``branch`` paths must be free parameters (`paths`), in any spelling of
    them."""
    from invglare.fit.stages import Stage

    if tables is None:
        return ()
    if not isinstance(tables, list):
        raise ConfigError(f"[[stage]] must be a list of tables, got {tables!r}")
    out = []
    for i, table in enumerate(tables):
        where = f"stage[{i}]"
        sec = Section(table, where)
        views = read_views(sec.get("views", dict, required=True), f"{where}.views")
        steps = sec.get("max_steps", int, default_steps)
        fixed = sec.get("fixed", list, [])
        branch = sec.get("branch", dict, {})
        sec.finish()
        if steps < 1:
            raise ConfigError(f"{where}.max_steps must be >= 1, got {steps}")
        spelt = [_free_path(forward, paths, path, f"{where}.fixed") for path in fixed]
        if len(set(spelt)) >= len(paths):
            raise ConfigError(f"{where}.fixed holds every free parameter; nothing is left to fit")
        branches = []
        for path, offsets in branch.items():
            if (
                not isinstance(offsets, list)
                or not offsets
                or not all(isinstance(o, int) and not isinstance(o, bool) for o in offsets)
                or len(set(offsets)) != len(offsets)
            ):
                raise ConfigError(
                    f"{where}.branch.{path} must be a list of distinct integer offsets "
                    f"(e.g. [-1, 0, 1]), got {offsets!r}"
                )
            branches.append((_free_path(forward, paths, path, f"{where}.branch"), tuple(offsets)))
        out.append(Stage(views, steps, tuple(spelt), tuple(branches)))
    return tuple(out)


def read_solver(table: Any) -> tuple[dict[str, Any], int, int]:
    """``(keyword arguments of invglare.fit.fit and "scan", n_starts, seed)`` of ``[solver]``."""
    from invglare.fit.solve import BATCH_MODES, SOLVERS

    sec = Section(table, "solver")
    solver = {
        "solver": sec.choice("solver", SOLVERS, "lm"),
        "max_steps": sec.get("max_steps", int, 100),
        "rtol": sec.get("rtol", float, 1e-6),
        "atol": sec.get("atol", float, 1e-8),
        "coarse_to_fine": tuple(sec.get("coarse_to_fine", list, [1])),
        "refine_top": sec.get("refine_top", int, 1),
        "batch": sec.choice("batch", BATCH_MODES, "vmap"),
    }
    scale = sec.get("covariance_scale", (str, float), "auto")
    if isinstance(scale, str) and scale not in ("auto", "chi2", "absolute"):
        raise ConfigError(
            f"solver.covariance_scale = {scale!r} is not auto, chi2, absolute or a number"
        )
    solver["covariance_scale"] = scale
    n_starts = sec.get("n_starts", int, 3)
    seed = sec.get("seed", int, 0)
    solver["scan"] = sec.get("scan", int, 0)
    sec.finish()
    if solver["scan"] and solver["scan"] < n_starts:
        raise ConfigError(
            f"solver.scan = {solver['scan']} must be 0 (off) or at least n_starts = {n_starts}"
        )
    factors = solver["coarse_to_fine"]
    if (
        not factors
        or factors[-1] != 1
        or any(isinstance(f, bool) or not isinstance(f, int) or f < 1 for f in factors)
    ):
        raise ConfigError(
            f"solver.coarse_to_fine must be integers >= 1 ending with 1, e.g. [2, 1]; got "
            f"{list(factors)}"
        )
    if n_starts < 1:
        raise ConfigError(f"solver.n_starts must be >= 1, got {n_starts}")
    if solver["max_steps"] < 1:
        raise ConfigError(f"solver.max_steps must be >= 1, got {solver['max_steps']}")
    return solver, n_starts, seed
