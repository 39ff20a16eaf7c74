"""Parameter spaces: which leaves of a model are free, their bounds, priors and transforms.

A fit never looks inside a model. It addresses each free parameter by a dotted
*path* into the model's pytree (``"aperture.shapes[0].diameter_mm"``,
``"obs.flux"``, ``"spectrum.wavelengths_nm[0]"``), writes values with
`eqx.tree_at`, and optimises an unconstrained *latent* vector from which the
physical values are recovered by per-parameter transforms.

**One path language.** Paths are the one way a value of a model is named: in Python,
in a fit config's ``[[free]]``, ``[[discrete]]`` and ``[[stage]].fixed``, in a synth
spec's ``[set]`` (configs spell model-config keys this way too, see
:mod:`invglare.config.paths`). A part that models store under different field names
has one name in a path (:data:`FIELD_ALIASES`): a model's aperture is ``aperture`` in
every model, so the pupil is ``model.aperture.pupil.diameter_mm`` in a Kakimoto eye and
in the temporal eye (whose field is ``eye``). The older spelling ``model.eye.…`` of the
temporal eye still works, with a :class:`DeprecationWarning` naming the new one, once
per spelling.

The transforms:

| transform  | physical `x` from latent `z`                 | used (``"auto"``) when     |
|------------|----------------------------------------------|----------------------------|
| `logit`    | ``lower + (upper - lower) * sigmoid(z)``     | both bounds finite         |
| `log`      | ``lower + exp(z)`` (``exp(z)`` for lower 0)  | ``lower >= 0``, upper inf  |
| `identity` | ``z``                                        | otherwise                  |

So bounds hold by construction for `logit` and `log`; for `identity` they are
enforced by :meth:`ParameterSpace.log_prior` only (``-inf`` outside).
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import re
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from invglare.errors import ConfigError

TRANSFORMS = ("auto", "log", "logit", "identity")
PRIORS = ("uniform", "normal", "lognormal")

#: Starts are drawn this far (as a fraction of the width) inside finite bounds: a
#: logit latent at the very edge is huge and its gradient vanishes.
START_MARGIN = 0.03

_TOKEN = re.compile(r"\.?([A-Za-z_][A-Za-z_0-9]*)|\[\s*(-?\d+(?:\s*,\s*-?\d+)*)\s*\]")

#: The name a path gives a part of a model, and the other field names models store it
#: under. A path naming the part by one of those (``model.eye.…`` for the temporal
#: model's aperture) is the older spelling: it still resolves, with a DeprecationWarning.
FIELD_ALIASES: dict[str, tuple[str, ...]] = {"aperture": ("eye",)}
_ALIAS_OF = {alias: name for name, aliases in FIELD_ALIASES.items() for alias in aliases}

#: Old spellings already warned about (each is warned about once per process).
_WARNED: set[str] = set()


# --------------------------------------------------------------------------------------
# paths


def parse_path(path: str) -> tuple[str | int, ...]:
    """Split a dotted path into steps: attribute names (``str``) and indices (``int``).

    ``[i]`` and ``[i, j]`` give one integer step per index. Whether an index
    selects a tuple element or an element of an array leaf is settled against a
    model by :func:`resolve_path`.

    **Example:** ``parse_path("aperture.shapes[0].center_mm[1]")`` gives
    ``("aperture", "shapes", 0, "center_mm", 1)``.
    """
    if not isinstance(path, str) or not path.strip():
        raise ConfigError(f"a parameter path must be a non-empty string, got {path!r}")
    text = path.strip()
    steps: list = []
    pos = 0
    while pos < len(text):
        m = _TOKEN.match(text, pos)
        if m is None or (pos == 0 and text[0] == "."):
            raise ConfigError(
                f"cannot parse parameter path {path!r} at {text[pos:]!r}; write e.g. "
                "'aperture.shapes[0].diameter_mm' or 'spectrum.wavelengths_nm[0]'"
            )
        if m.group(1) is not None:
            steps.append(m.group(1))
        else:
            steps.extend(int(i) for i in m.group(2).split(","))
        pos = m.end()
    return tuple(steps)


def _has_field(node: Any, name: str) -> bool:
    """Whether `node` holds `name` as data: a dataclass field of a Module (not a method or
    property of the same name: the temporal model's ``aperture()`` renders its raster), or
    an attribute of another object."""
    if isinstance(node, list | tuple | dict):
        return False
    if dataclasses.is_dataclass(node):
        return name in {f.name for f in dataclasses.fields(node)}
    return hasattr(node, name)


def _field(node: Any, name: str) -> str | None:
    """The field of `node` that a path step `name` names (an alias resolved), or None."""
    if _has_field(node, name):
        return name
    for alias in FIELD_ALIASES.get(name, ()):
        if _has_field(node, alias):
            return alias
    return None


def _spelling(node: Any, field: str) -> str:
    """How a path spells `node`'s `field`: its alias-table name where `node` has no field
    of that name (``eye`` of the temporal model is spelt ``aperture``)."""
    name = _ALIAS_OF.get(field)
    return name if name is not None and not _has_field(node, name) else field


def _format_path(tree: Any, keys) -> str:
    out = ""
    node = tree
    for k in keys:
        if isinstance(k, jax.tree_util.GetAttrKey):
            out += f".{_spelling(node, k.name)}"
            node = getattr(node, k.name, None)
        elif isinstance(k, jax.tree_util.SequenceKey):
            out += f"[{k.idx}]"
            node = node[k.idx] if isinstance(node, list | tuple) else None
        elif isinstance(k, jax.tree_util.DictKey):
            out += f"[{k.key!r}]"
            node = None
        else:  # FlattenedIndexKey and friends: not addressable by name
            out += f"<{k}>"
            node = None
    return out.lstrip(".")


def _is_float_array(x) -> bool:
    return isinstance(x, jax.Array | np.ndarray) and jnp.issubdtype(x.dtype, jnp.floating)


def valid_paths(model: Any) -> list[str]:
    """Every scalar a :class:`Parameter` can address in `model`, as path strings.

    Scalar float leaves are listed by their own path; each element of a float
    array leaf is listed with its index (``"center_mm[0]"``, ``"weights_xyz[0, 2]"``).
    Static fields and integer leaves are configuration, not parameters, and are
    not listed. Paths are spelt in the one path language (:data:`FIELD_ALIASES`).

    **Example:** for ``Forward(AperturePSF(...), Observation(...))`` this includes
    ``"model.aperture.shapes[0].diameter_mm"`` and ``"obs.flux"``.
    """
    out: list[str] = []
    for keys, leaf in jax.tree_util.tree_flatten_with_path(model)[0]:
        if not _is_float_array(leaf):
            continue
        base = _format_path(model, keys)
        if leaf.ndim == 0:
            out.append(base)
        else:
            for idx in np.ndindex(*leaf.shape):
                out.append(f"{base}[{', '.join(str(i) for i in idx)}]")
    return out


def _canonical(steps: Sequence) -> str:
    out = ""
    for s in steps:
        out += f"[{s}]" if isinstance(s, int) else f".{s}"
    return out.lstrip(".")


def _unknown_path_error(path: str, model: Any, why: str) -> ConfigError:
    valid = valid_paths(model)
    close = difflib.get_close_matches(path, valid, n=3, cutoff=0.5)
    hint = f" Did you mean {', '.join(repr(c) for c in close)}?" if close else ""
    shown = valid if len(valid) <= 60 else [*valid[:60], f"... and {len(valid) - 60} more"]
    return ConfigError(
        f"parameter path {path!r} {why}.{hint} Valid paths: {', '.join(shown) or '(none)'}"
    )


def _respelt(path: str, renames: Mapping[int, str]) -> str:
    """`path` with its `renames` (``{position of a name step: new name}``) applied, the rest
    of the text as written."""
    text = path.strip()
    out, pos, k = [], 0, 0
    while pos < len(text):
        m = _TOKEN.match(text, pos)
        piece = m.group(0)
        if m.group(1) is not None:
            if k in renames:
                piece = piece.replace(m.group(1), renames[k])
            k += 1
        else:
            k += len(m.group(2).split(","))
        out.append(piece)
        pos = m.end()
    return "".join(out)


def _walk(model: Any, path: str, steps: tuple) -> tuple[Any, tuple, tuple[int, ...], str]:
    """Follow `steps` into `model`: ``(node, field steps taken, element index, spelling)``.

    The walk stops at the first float array (the rest of the steps index it) or after the
    last step. `spelling` is `path` in the one path language; an older spelling is
    warned about (once).
    """
    node = model
    taken: list = []
    renames: dict[int, str] = {}
    for depth, step in enumerate(steps):
        if _is_float_array(node):
            index = tuple(steps[depth:])
            if not all(isinstance(i, int) for i in index) or len(index) != node.ndim:
                raise _unknown_path_error(
                    path, model, f"indexes an array of shape {node.shape} with {list(index)}"
                )
            if any(not -n <= i < n for i, n in zip(index, node.shape, strict=True)):
                raise _unknown_path_error(
                    path, model, f"is out of range for an array of shape {node.shape}"
                )
            index = tuple(i % n for i, n in zip(index, node.shape, strict=True))
            return node, tuple(taken), index, _warn_old_spelling(path, renames)
        if isinstance(step, int):
            if not isinstance(node, list | tuple) or not -len(node) <= step < len(node):
                raise _unknown_path_error(path, model, "does not exist")
            node = node[step]
            taken.append(step)
            continue
        field = _field(node, step)
        if field is None:
            raise _unknown_path_error(path, model, "does not exist")
        spelt = _spelling(node, field)
        if spelt != step:
            renames[depth] = spelt
        node = getattr(node, field)
        taken.append(field)
    return node, tuple(taken), (), _warn_old_spelling(path, renames)


def _warn_old_spelling(path: str, renames: Mapping[int, str]) -> str:
    if not renames:
        return path
    new = _respelt(path, renames)
    if path not in _WARNED:
        _WARNED.add(path)
        warnings.warn(
            f"the parameter path {path!r} is an older spelling; write {new!r} (a model's "
            "aperture is 'model.aperture' in every model)",
            DeprecationWarning,
            stacklevel=4,
        )
    return new


def resolve_path(
    model: Any, path: str, steps: tuple | None = None
) -> tuple[tuple, tuple[int, ...]]:
    """Check `path` against `model`; return ``(steps to the array leaf, element index)``.

    Raises :class:`~invglare.errors.ConfigError` listing the valid paths when the
    path does not exist, does not end at a float leaf, or does not pick one scalar.
    `steps` are the already parsed steps of `path`, if at hand. The returned steps are
    the model's own field names (an alias of :data:`FIELD_ALIASES` resolved).
    """
    if steps is None:
        steps = parse_path(path)
    node, taken, index, _ = _walk(model, path, steps)
    if index:
        return taken, index
    if not _is_float_array(node):
        raise _unknown_path_error(path, model, "does not end at a float array leaf")
    if node.ndim != 0:
        raise _unknown_path_error(
            path, model, f"is an array of shape {node.shape}; address one element"
        )
    return taken, ()


def spelling(model: Any, path: str) -> str:
    """`path` in the one path language: an older spelling (``model.eye.…`` of the temporal
    model) comes back in the new one (``model.aperture.…``), with a DeprecationWarning
    the first time. Raises :class:`~invglare.errors.ConfigError` if `path` does not exist.

    **Example:** ``spelling(Forward(temporal_model, obs), "model.eye.pupil.diameter_mm")``
    is ``"model.aperture.pupil.diameter_mm"``.
    """
    resolve_path(model, path)
    return _walk(model, path, parse_path(path))[3]


def read_path(model: Any, path: str) -> float:
    """The value `model` holds at the scalar `path`, as a Python float.

    **Example:** ``read_path(forward, "obs.flux")``.
    """
    steps, index = resolve_path(model, path)
    leaf = np.asarray(_getter(steps)(model))
    return float(leaf[index] if index else leaf)


def _static_ints(model: Any) -> list[str]:
    """Paths of the integer-valued static fields of `model`'s modules (its structural choices)."""
    out: list[str] = []

    def visit(node: Any, prefix: str) -> None:
        if isinstance(node, list | tuple):
            for i, child in enumerate(node):
                visit(child, f"{prefix}[{i}]")
            return
        if not isinstance(node, eqx.Module):
            return
        for f in dataclasses.fields(node):
            value = getattr(node, f.name, None)
            name = f"{prefix}.{_spelling(node, f.name)}".lstrip(".")
            if f.metadata.get("static", False):
                if isinstance(value, int) and not isinstance(value, bool):
                    out.append(name)
            else:
                visit(value, name)

    visit(model, "")
    return out


def static_int(model: Any, path: str) -> int:
    """The integer static field (a structural choice: ``n_blades``, ``n_max``) at `path`.

    These are not fittable leaves: a ``[[discrete]]`` table tries them value by value,
    each value a rebuilt model. Raises :class:`~invglare.errors.ConfigError` naming the
    path and listing the valid ones when `path` does not reach one.

    **Example:** ``static_int(forward, "model.aperture.diaphragm.n_blades")`` is ``6``.
    """
    try:
        node, _, index, _ = _walk(model, path, parse_path(path))
    except ConfigError:
        node, index = None, ()
    if isinstance(node, int) and not isinstance(node, bool) and not index:
        return node
    valid = _static_ints(model)
    what = (
        "is a fitted value (a float leaf): fit it as a [[free]] parameter"
        if _is_float_array(node) or index
        else "is not an integer choice of the model"
    )
    raise ConfigError(
        f"the path {path!r} {what}; integer choices of this model: {', '.join(valid) or '(none)'}"
    )


def _getter(steps: tuple):
    def where(tree):
        node = tree
        for s in steps:
            node = node[s] if isinstance(s, int) else getattr(node, s)
        return node

    return where


# --------------------------------------------------------------------------------------
# priors


@dataclasses.dataclass(frozen=True)
class Prior:
    """A prior density on one physical value (truncated to the parameter's bounds).

    - ``Prior("uniform")``: flat within the bounds (the default).
    - ``Prior("normal", mean, std)``: Gaussian in the physical value.
    - ``Prior("lognormal", mean, std)``: Gaussian in ``log(x)``; `mean` and `std`
      are of ``log(x)`` (so ``exp(mean)`` is the median).
    """

    kind: str = "uniform"
    mean: float = 0.0
    std: float = 1.0

    def __post_init__(self):
        if self.kind not in PRIORS:
            raise ConfigError(f"prior kind {self.kind!r} is not one of {', '.join(PRIORS)}")
        if self.kind != "uniform" and not (math.isfinite(self.std) and self.std > 0):
            raise ConfigError(f"a {self.kind} prior needs std > 0, got {self.std!r}")

    def log_density(self, x: Array) -> Array:
        """Log density (up to a constant for the truncation) at physical `x`."""
        if self.kind == "normal":
            return -0.5 * ((x - self.mean) / self.std) ** 2 - math.log(
                self.std * math.sqrt(2 * math.pi)
            )
        if self.kind == "lognormal":
            lx = jnp.log(jnp.where(x > 0, x, 1.0))
            val = -0.5 * ((lx - self.mean) / self.std) ** 2 - lx
            return jnp.where(x > 0, val - math.log(self.std * math.sqrt(2 * math.pi)), -jnp.inf)
        return jnp.zeros_like(x)


def _as_prior(prior) -> Prior | None:
    if prior is None or isinstance(prior, Prior):
        return prior
    if isinstance(prior, str):
        return Prior(prior)
    if isinstance(prior, Sequence) and prior and isinstance(prior[0], str):
        return Prior(prior[0], *(float(v) for v in prior[1:]))
    if isinstance(prior, Mapping):
        return Prior(**prior)
    raise ConfigError(
        f"prior must be None, 'uniform', ('normal', mean, std) or ('lognormal', mean_log, "
        f"std_log), got {prior!r}"
    )


# --------------------------------------------------------------------------------------
# one parameter


@dataclasses.dataclass(frozen=True)
class Parameter:
    """One free scalar: where it lives, its bounds, starting value, prior and transform.

    **Arguments:**

    - `path`: dotted path into the model (see :func:`valid_paths`).
    - `lower`, `upper`: bounds in the parameter's physical unit (``-inf``/``inf`` allowed).
    - `init`: starting value, strictly inside finite bounds.
    - `prior`: ``None`` (uniform within the bounds), a :class:`Prior`, or a tuple
      such as ``("normal", 3.0, 0.5)``.
    - `transform`: ``"auto"`` (see the module table), ``"log"``, ``"logit"`` or ``"identity"``.

    **Example:**

    ```python
    Parameter("model.aperture.shapes[0].diameter_mm", 2.0, 5.0, init=3.5)  # logit
    Parameter("obs.flux", 0.0, float("inf"), init=1e6)                     # log
    ```
    """

    path: str
    lower: float
    upper: float
    init: float
    prior: Prior | None = None
    transform: str = "auto"
    # The parsed path, once: it is the same for every model the parameter is applied to.
    steps: tuple = dataclasses.field(init=False, repr=False, compare=False)

    def __post_init__(self):
        name = f"parameter {self.path!r}"
        object.__setattr__(self, "steps", parse_path(self.path))
        try:
            lo, hi, x0 = float(self.lower), float(self.upper), float(self.init)
        except (TypeError, ValueError):
            raise ConfigError(
                f"{name}: lower, upper and init must be numbers, got "
                f"{self.lower!r}, {self.upper!r}, {self.init!r}"
            ) from None
        object.__setattr__(self, "lower", lo)
        object.__setattr__(self, "upper", hi)
        object.__setattr__(self, "init", x0)
        object.__setattr__(self, "prior", _as_prior(self.prior))
        if math.isnan(lo) or math.isnan(hi) or not math.isfinite(x0):
            raise ConfigError(f"{name}: bounds must not be NaN and init must be finite")
        if not lo < hi:
            raise ConfigError(f"{name}: lower bound {lo:g} must be < upper bound {hi:g}")
        if self.transform not in TRANSFORMS:
            raise ConfigError(
                f"{name}: transform {self.transform!r} is not one of {', '.join(TRANSFORMS)}"
            )
        kind = self.kind
        if kind == "logit" and not (math.isfinite(lo) and math.isfinite(hi)):
            raise ConfigError(
                f"{name}: the logit transform needs finite bounds, got [{lo:g}, {hi:g}]; "
                "use transform='log' or 'identity' for an open interval"
            )
        if kind == "log" and not math.isfinite(lo):
            raise ConfigError(f"{name}: the log transform needs a finite lower bound, got {lo:g}")
        # A transformed init on its bound would have an infinite latent.
        open_bounds = kind in ("log", "logit")
        inside = (lo < x0 < hi) if open_bounds else (lo <= x0 <= hi)
        if not inside:
            strict = " strictly" if open_bounds else ""
            raise ConfigError(
                f"{name}: init {x0:g} is not{strict} inside the bounds [{lo:g}, {hi:g}]"
            )

    @property
    def kind(self) -> str:
        """The transform actually used (``"auto"`` resolved)."""
        if self.transform != "auto":
            return self.transform
        if math.isfinite(self.lower) and math.isfinite(self.upper):
            return "logit"
        if self.lower >= 0.0 and self.upper == math.inf:
            return "log"
        return "identity"

    # Scalar transforms; `z` and `x` are JAX scalars (or arrays, elementwise).

    def to_physical(self, z: Array) -> Array:
        kind = self.kind
        if kind == "logit":
            return self.lower + (self.upper - self.lower) * jax.nn.sigmoid(z)
        if kind == "log":
            return self.lower + jnp.exp(z) if self.lower != 0.0 else jnp.exp(z)
        return z

    def to_latent(self, x: Array) -> Array:
        kind = self.kind
        if kind == "logit":
            u = (x - self.lower) / (self.upper - self.lower)
            return jnp.log(u) - jnp.log1p(-u)
        if kind == "log":
            return jnp.log(x - self.lower)
        return x

    def log_abs_dx_dz(self, z: Array) -> Array:
        """``log |d x / d z|`` of the transform at latent `z`."""
        kind = self.kind
        if kind == "logit":
            return (
                math.log(self.upper - self.lower) + jax.nn.log_sigmoid(z) + jax.nn.log_sigmoid(-z)
            )
        if kind == "log":
            return z
        return jnp.zeros_like(z)

    def dx_dz(self, z: Array) -> Array:
        return jnp.exp(self.log_abs_dx_dz(z))

    def log_prior(self, x: Array) -> Array:
        inside = (x >= self.lower) & (x <= self.upper)
        if self.prior is None or self.prior.kind == "uniform":
            width = self.upper - self.lower
            val = jnp.full_like(x, -math.log(width) if math.isfinite(width) else 0.0)
        else:
            val = self.prior.log_density(x)
        return jnp.where(inside, val, -jnp.inf)


# --------------------------------------------------------------------------------------
# the space


@dataclasses.dataclass(frozen=True)
class ParameterSpace:
    """The free parameters of a fit, in a fixed order, and the maps latent ⇄ physical ⇄ model.

    **Arguments:**

    - `parameters`: the parameters of interest.
    - `nuisance`: parameters fitted alongside but not of interest (source flux,
      background, centre, ...). They follow the parameters in the latent vector and
      are *not* randomised by :meth:`sample_starts` (their starting guesses usually
      come from the data, see :meth:`invglare.fit.Observation.from_target`).

    The space is hashable (it is static configuration under `jit`). Physical and
    latent values are 1-D arrays in the order of :attr:`paths`.

    **Example:**

    ```python
    space = ParameterSpace(
        [Parameter("model.aperture.shapes[0].diameter_mm", 2.0, 5.0, init=3.5)],
        nuisance=[Parameter("obs.flux", 0.0, float("inf"), init=1e6)],
    )
    forward = space.apply(forward, space.from_latent(space.initial_latent()))
    ```
    """

    parameters: tuple[Parameter, ...]
    nuisance: tuple[Parameter, ...] = ()

    def __init__(self, parameters: Sequence[Parameter], nuisance: Sequence[Parameter] = ()):
        params = tuple(parameters)
        nuis = tuple(nuisance)
        for p in (*params, *nuis):
            if not isinstance(p, Parameter):
                raise ConfigError(f"expected Parameter objects, got {type(p).__name__}: {p!r}")
        if not params and not nuis:
            raise ConfigError("a parameter space needs at least one free parameter")
        seen: set[str] = set()
        for p in (*params, *nuis):
            key = _canonical(p.steps)
            if key in seen:
                raise ConfigError(f"parameter {p.path!r} is listed twice")
            seen.add(key)
        object.__setattr__(self, "parameters", params)
        object.__setattr__(self, "nuisance", nuis)

    # ---- bookkeeping

    @property
    def all(self) -> tuple[Parameter, ...]:
        return (*self.parameters, *self.nuisance)

    @property
    def paths(self) -> tuple[str, ...]:
        return tuple(p.path for p in self.all)

    @property
    def size(self) -> int:
        return len(self.all)

    @property
    def is_nuisance(self) -> tuple[bool, ...]:
        return (False,) * len(self.parameters) + (True,) * len(self.nuisance)

    def check(self, model: Any) -> None:
        """Raise :class:`~invglare.errors.ConfigError` unless every path exists in `model`
        and no two name the same value (an older and a newer spelling of one path)."""
        seen: dict[tuple, str] = {}
        for p in self.all:
            where = resolve_path(model, p.path, p.steps)
            if where in seen:
                raise ConfigError(
                    f"parameters {seen[where]!r} and {p.path!r} name the same value; free it once"
                )
            seen[where] = p.path

    def values_from(self, values: Mapping[str, float] | ArrayLike) -> Array:
        """A 1-D physical vector from a mapping ``path -> value`` or a sequence."""
        if isinstance(values, Mapping):
            missing = [p for p in self.paths if p not in values]
            if missing:
                raise ConfigError(f"no value given for {', '.join(missing)}")
            values = [values[p] for p in self.paths]
        arr = jnp.asarray(values, dtype=jnp.result_type(float))
        if arr.shape[-1:] != (self.size,):
            raise ConfigError(
                f"expected {self.size} values ({', '.join(self.paths)}), got shape {arr.shape}"
            )
        return arr

    def as_dict(self, values: ArrayLike) -> dict[str, float]:
        """``{path: float}`` from a 1-D physical vector."""
        arr = np.asarray(values, dtype=float)
        return {p: float(v) for p, v in zip(self.paths, arr, strict=True)}

    # ---- transforms

    def from_latent(self, latent: Float[ArrayLike, "*batch p"]) -> Float[Array, "*batch p"]:
        """Physical values from latent ones (any leading batch axes)."""
        z = jnp.asarray(latent)
        return jnp.stack(self.from_latent_parts([z[..., i] for i in range(self.size)]), axis=-1)

    def from_latent_parts(self, parts: Sequence[Array]) -> list[Array]:
        """`from_latent` one parameter at a time: a list of physical values from a list of
        latent ones. Kept apart (never stacked into one vector), a tangent on one of them
        stays on that parameter's path through the model (see `apply`)."""
        if len(parts) != self.size:
            raise ConfigError(f"expected {self.size} latent values, got {len(parts)}")
        return [p.to_physical(z) for z, p in zip(parts, self.all, strict=True)]

    def to_latent(
        self, values: Mapping[str, float] | Float[ArrayLike, "*batch p"]
    ) -> Float[Array, "*batch p"]:
        """Latent values from physical ones (a mapping or an array, any leading batch axes)."""
        x = self.values_from(values)
        cols = [p.to_latent(x[..., i]) for i, p in enumerate(self.all)]
        return jnp.stack(cols, axis=-1)

    def initial_values(self) -> Float[Array, " p"]:
        return jnp.asarray([p.init for p in self.all], dtype=jnp.result_type(float))

    def initial_latent(self) -> Float[Array, " p"]:
        return self.to_latent(self.initial_values())

    def jacobian_diag(self, latent: Float[ArrayLike, " p"]) -> Float[Array, " p"]:
        """``d x_i / d z_i`` (the transforms act elementwise, so the Jacobian is diagonal)."""
        z = jnp.asarray(latent)
        return jnp.stack([p.dx_dz(z[..., i]) for i, p in enumerate(self.all)], axis=-1)

    def log_det_jacobian(self, latent: Float[ArrayLike, "*batch p"]) -> Float[Array, "*batch"]:
        """``log |det d x / d z|``: add it to a physical log-density to sample in latent space."""
        z = jnp.asarray(latent)
        terms = [p.log_abs_dx_dz(z[..., i]) for i, p in enumerate(self.all)]
        return sum(terms[1:], terms[0])

    def log_prior(self, values: Float[ArrayLike, "*batch p"]) -> Float[Array, "*batch"]:
        """Sum of the parameters' log prior densities at physical `values` (``-inf`` outside)."""
        x = jnp.asarray(values)
        terms = [p.log_prior(x[..., i]) for i, p in enumerate(self.all)]
        return sum(terms[1:], terms[0])

    # ---- the model

    def apply(self, model: Any, values: Float[ArrayLike, " p"] | Sequence[Array]) -> Any:
        """`model` with each free leaf replaced by the physical value in `values`.

        `values` is a vector or a list of scalars (as from `from_latent_parts`): a forward
        derivative in one scalar of a list then reaches only the leaves and computations
        that depend on it, whereas every entry of a vector shares the vector's tangent.
        Values are cast to the leaf's dtype; array elements are written with
        ``.at[i].set``. Works under `jit`, `vmap` and `grad`.
        """
        if isinstance(values, list | tuple):
            xs = list(values)
        else:
            x = jnp.asarray(values)
            xs = [x[i] for i in range(x.shape[0])]
        for p, value in zip(self.all, xs, strict=True):
            steps, index = resolve_path(model, p.path, p.steps)
            where = _getter(steps)
            leaf = where(model)
            v = jnp.asarray(value).astype(leaf.dtype)
            if index:
                model = eqx.tree_at(where, model, replace_fn=lambda a, v=v, k=index: a.at[k].set(v))
            else:
                model = eqx.tree_at(where, model, v)
        return model

    def read(self, model: Any) -> Float[Array, " p"]:
        """The current physical values of the free leaves of `model`."""
        vals = []
        for p in self.all:
            steps, index = resolve_path(model, p.path, p.steps)
            leaf = _getter(steps)(model)
            vals.append(leaf[index] if index else leaf)
        return jnp.stack([jnp.asarray(v, dtype=jnp.result_type(float)) for v in vals])

    # ---- starts

    def sample_starts(self, key: PRNGKeyArray, n: int) -> Float[Array, "n p"]:
        """`n` latent starting points spread across the bounds (a Latin hypercube).

        Each parameter's range is cut into `n` equal strata, one draw per stratum,
        shuffled independently per parameter, so the starts cover the bounds even
        for small `n`. Finite bounds: uniform in the physical value, kept
        `START_MARGIN` of the width away from the edges. A lower bound only: a
        factor of up to 3 either side of ``init - lower`` (log-uniform). No finite
        bound: ``init ± max(|init|, 1) / 2``. Nuisance parameters stay at `init`.
        Start 0 is not special; pass your own starts to :func:`invglare.fit.fit`
        to include the initial values.
        """
        if int(n) != n or n < 1:
            raise ConfigError(f"the number of starts must be an integer >= 1, got {n!r}")
        # One compiled program instead of a few dozen eagerly dispatched small ones.
        return _sample_starts(self, key, int(n))

    def _sample_starts_impl(self, key: PRNGKeyArray, n: int) -> Float[Array, "n p"]:
        keys = jax.random.split(key, 2 * self.size)
        cols = []
        for i, p in enumerate(self.all):
            if self.is_nuisance[i]:
                cols.append(jnp.full((n,), p.init))
                continue
            strata = jax.random.permutation(keys[2 * i], n)
            u = (strata + jax.random.uniform(keys[2 * i + 1], (n,))) / n
            if math.isfinite(p.lower) and math.isfinite(p.upper):
                m = START_MARGIN
                x = p.lower + (p.upper - p.lower) * (m + (1 - 2 * m) * u)
            elif math.isfinite(p.lower):
                x = p.lower + (p.init - p.lower) * jnp.exp(math.log(3.0) * (2 * u - 1))
            else:
                scale = max(abs(p.init), 1.0)
                x = p.init + scale * (u - 0.5)
            cols.append(jnp.clip(x, p.lower, p.upper))
        return self.to_latent(jnp.stack(cols, axis=-1))


_sample_starts = jax.jit(ParameterSpace._sample_starts_impl, static_argnums=(0, 2))
