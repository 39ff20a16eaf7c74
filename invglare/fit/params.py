"""Parameter spaces: which leaves of a model are free, their bounds, priors and transforms.

Each free parameter is named by its path into the model (:mod:`invglare.fit.paths`, the
one path language of configs and Python). The fit optimises an unconstrained *latent*
vector from which the physical values are recovered by per-parameter transforms:

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
import math
from collections.abc import Mapping, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from invglare.errors import ConfigError
from invglare.fit.paths import (
    FIELD_ALIASES,
    leaf_getter,
    parse_path,
    path_of_steps,
    read_path,
    resolve_path,
    spelling,
    static_int,
    valid_paths,
)

# Path functions are part of this module's face too (``invglare.fit.params.resolve_path``).
__all__ = [
    "FIELD_ALIASES",
    "PRIORS",
    "START_MARGIN",
    "TRANSFORMS",
    "Parameter",
    "ParameterSpace",
    "Prior",
    "parse_path",
    "read_path",
    "resolve_path",
    "spelling",
    "static_int",
    "valid_paths",
]

TRANSFORMS = ("auto", "log", "logit", "identity")
PRIORS = ("uniform", "normal", "lognormal")

#: Starts are drawn this far (as a fraction of the width) inside finite bounds: a
#: logit latent at the very edge is huge and its gradient vanishes.
START_MARGIN = 0.03


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
            key = path_of_steps(p.steps)
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

    def structure(self) -> ParameterSpace:
        """This space with every `init` replaced by one fixed value inside its bounds.

        The latent ⇄ physical maps and the priors do not read `init`; a residual function
        holds this copy as its static part, so fits of photos whose starting guesses differ
        (flux, background, centre from each photo) share their compiled programs.
        """

        def fixed(p: Parameter) -> Parameter:
            lo, hi = p.lower, p.upper
            if math.isfinite(lo) and math.isfinite(hi):
                init = 0.5 * (lo + hi)
            elif math.isfinite(lo):
                init = lo + 1.0
            elif math.isfinite(hi):
                init = hi - 1.0
            else:
                init = 0.0
            return dataclasses.replace(p, init=init)

        return ParameterSpace(list(map(fixed, self.parameters)), list(map(fixed, self.nuisance)))

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
            where = leaf_getter(steps)
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
            leaf = leaf_getter(steps)(model)
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
