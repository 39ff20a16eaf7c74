"""Populations of synthetic photos: a synth spec whose values are drawn per member.

A synth spec (:mod:`invglare.config.synth`) with a ``[population]`` table makes `size`
photos instead of one. Member `i` is the spec with the values of
``[population.set]`` (model parameter paths), ``[population.observation]`` (observation
fields) and ``[population.config]`` (model-config keys, such as the eye's random draw
``model.eye.seed``) drawn for it, and the noise seed ``synth.seed + i``:

```toml
[population]
size = 16
seed = 2024                     # draws the members' values (numpy's default generator)
name = "eye"                    # members eye_00, eye_01, ... (default: the spec's out)

[population.set]
"model.aperture.pupil.diameter_mm" = ["uniform", 2.5, 4.0]
"model.aperture.upper_lashes.count" = ["integers", 32, 46]      # both ends included

[population.observation]
flux = ["loguniform", 5e7, 2e8]
dx_px = ["normal", 0.0, 0.2]

[population.config]
"model.eye.seed" = ["sequence", 1000]                            # 1000, 1001, ...
```

Distributions: ``["uniform", low, high]``, ``["loguniform", low, high]``, ``["normal",
mean, std]``, ``["lognormal", mean_log, std_log]``, ``["integers", low, high]`` and
``["sequence", start]`` or ``["sequence", start, step]``. Each key draws from its own
stream (``numpy.random.SeedSequence(seed).spawn``, in the order the keys are listed), so
the same spec always draws the same population.

**Example:**

```python
population = read_population(config["population"], "population")
values = population.draw()     # [{"set": {...}, "observation": {...}, "config": {...}}, ...]
```
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Mapping
from typing import Any

import numpy as np

from invglare.config.section import Section
from invglare.errors import ConfigError

#: Distributions and how many numbers each takes.
DISTRIBUTIONS = {
    "uniform": (2,),
    "loguniform": (2,),
    "normal": (2,),
    "lognormal": (2,),
    "integers": (2,),
    "sequence": (1, 2),
}
#: The tables of drawn values.
GROUPS = ("set", "observation", "config")
_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")


@dataclasses.dataclass(frozen=True)
class Distribution:
    """One drawn value: `kind` (a key of :data:`DISTRIBUTIONS`) and its numbers."""

    kind: str
    args: tuple[float, ...]

    def draw(self, rng: np.random.Generator, n: int) -> list[float | int]:
        """`n` values (ints for ``integers`` and ``sequence``)."""
        a = self.args
        if self.kind == "uniform":
            return [float(v) for v in rng.uniform(a[0], a[1], n)]
        if self.kind == "loguniform":
            return [float(v) for v in np.exp(rng.uniform(math.log(a[0]), math.log(a[1]), n))]
        if self.kind == "normal":
            return [float(v) for v in rng.normal(a[0], a[1], n)]
        if self.kind == "lognormal":
            return [float(v) for v in rng.lognormal(a[0], a[1], n)]
        if self.kind == "integers":
            return [int(v) for v in rng.integers(int(a[0]), int(a[1]), n, endpoint=True)]
        step = int(a[1]) if len(a) > 1 else 1
        return [int(a[0]) + step * i for i in range(n)]


def read_distribution(value: Any, where: str) -> Distribution:
    """A ``[kind, numbers...]`` list (module docstring) as a :class:`Distribution`."""
    if not (isinstance(value, list) and value and isinstance(value[0], str)):
        raise ConfigError(
            f"{where} must be a distribution [kind, numbers...] with kind one of "
            f"{', '.join(DISTRIBUTIONS)}, e.g. ['uniform', 2.5, 4.0]; got {value!r}"
        )
    kind, args = value[0], value[1:]
    if kind not in DISTRIBUTIONS:
        valid = ", ".join(DISTRIBUTIONS)
        raise ConfigError(f"{where}: distribution {kind!r} is not one of {valid}")
    if len(args) not in DISTRIBUTIONS[kind]:
        counts = " or ".join(str(c) for c in DISTRIBUTIONS[kind])
        raise ConfigError(f"{where}: {kind} takes {counts} number(s), got {args!r}")
    if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in args) or not all(
        math.isfinite(v) for v in args
    ):
        raise ConfigError(f"{where}: the numbers of {kind} must be finite numbers, got {args!r}")
    if kind in ("integers", "sequence") and not all(float(v).is_integer() for v in args):
        raise ConfigError(f"{where}: the numbers of {kind} must be integers, got {args!r}")
    if kind in ("uniform", "loguniform", "integers") and not args[0] <= args[1]:
        raise ConfigError(f"{where}: {kind} needs low <= high, got {args!r}")
    if kind == "loguniform" and not args[0] > 0:
        raise ConfigError(f"{where}: loguniform needs low > 0, got {args!r}")
    if kind in ("normal", "lognormal") and not args[1] >= 0:
        raise ConfigError(f"{where}: {kind} needs std >= 0, got {args!r}")
    return Distribution(kind, tuple(float(v) for v in args))


@dataclasses.dataclass(frozen=True)
class Population:
    """A checked ``[population]`` table: how many members, their names, what is drawn."""

    size: int
    seed: int
    name: str | None
    draws: dict[str, dict[str, Distribution]]

    def draw(self) -> list[dict[str, dict[str, float | int]]]:
        """Each member's values, ``{"set": {...}, "observation": {...}, "config": {...}}``."""
        keys = [(group, key) for group in GROUPS for key in self.draws[group]]
        streams = np.random.SeedSequence(self.seed).spawn(len(keys))
        columns = {
            (group, key): self.draws[group][key].draw(np.random.default_rng(stream), self.size)
            for (group, key), stream in zip(keys, streams, strict=True)
        }
        return [
            {g: {k: columns[(g, k)][i] for k in self.draws[g]} for g in GROUPS}
            for i in range(self.size)
        ]

    def member_name(self, default: str, i: int) -> str:
        width = max(2, len(str(self.size - 1)))
        return f"{self.name or default}_{i:0{width}d}"


def read_population(table: Any, where: str = "population") -> Population:
    """Check a ``[population]`` table (module docstring).

    **Raises:** :class:`~invglare.errors.ConfigError` naming the key for unknown keys,
    a size below 1, a bad name, observation fields that do not exist, model paths that
    do not start with ``model.``, and distributions that are not one.
    """
    from invglare.config.synth import OBSERVATION_KEYS

    sec = Section(table, where)
    size = sec.get("size", int, required=True)
    seed = sec.get("seed", int, 0)
    name = sec.get("name", str, None)
    raw = {group: sec.get(group, dict, {}) for group in GROUPS}
    sec.finish()
    if size < 1:
        raise ConfigError(f"{where}.size must be >= 1, got {size}")
    if seed < 0:
        raise ConfigError(f"{where}.seed must be >= 0, got {seed}")
    if name is not None and not _NAME.match(name):
        raise ConfigError(f"{where}.name = {name!r} must be a plain name (letters, digits, _ - .)")
    draws: dict[str, dict[str, Distribution]] = {}
    for group, entries in raw.items():
        draws[group] = {}
        for key, value in entries.items():
            here = f"{where}.{group}.{key!r}"
            if group == "set" and not key.startswith("model."):
                raise ConfigError(f"{here}: a model path must start with 'model.'")
            if group == "observation" and key not in OBSERVATION_KEYS:
                raise ConfigError(
                    f"{here} is not an observation field; valid: {', '.join(OBSERVATION_KEYS)}"
                )
            draws[group][key] = read_distribution(value, here)
    if not any(draws.values()):
        raise ConfigError(f"[{where}] draws nothing: add [{where}.set], .observation or .config")
    return Population(size, seed, name, draws)


def member_values(member: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """One member's drawn values as one flat ``{key: value}`` (for the population table)."""
    return {key: value for group in GROUPS for key, value in member[group].items()}
