"""Model-config keys spelt as parameter paths, and back: one path language for every config.

A value of a model is named in one language everywhere a config names one (``[[free]]``,
``[[discrete]]`` and ``[[stage]].fixed`` of a fit config, ``[set]`` of a synth spec): its
*parameter path*, the dotted path into the fit's ``Forward(model, obs)`` pytree with
``[i]`` indices (:mod:`invglare.fit.params`). A model's aperture is ``model.aperture`` in
every model, whatever the model config calls its table:

| model kind | model config key                      | parameter path                       |
|------------|---------------------------------------|--------------------------------------|
| eye        | ``model.eye.pupil.diameter_mm``       | ``model.aperture.pupil.diameter_mm`` |
| eye        | ``model.eye.lashes_upper.n_max``      | ``model.aperture.upper_lashes.n_max``|
| eye        | ``model.eye.particles.1.count``       | ``model.aperture.particles[1].count``|
| camera     | ``model.camera.diaphragm.n_blades``   | ``model.aperture.diaphragm.n_blades``|
| camera     | ``model.camera.cross_screen.spacing_mm`` | ``model.aperture.filter.spacing_mm`` |
| aperture   | ``model.shapes.0.diameter_mm``        | ``model.aperture.shapes[0].diameter_mm`` |
| temporal   | ``model.eye.lids.upper_opening_mm``   | ``model.aperture.lids.upper_opening_mm`` |
| veiling    | ``model.lens.sensor_reflectance``     | ``model.ghosts.lens.sensor_reflectance`` |

Older configs named a ``[[discrete]]`` choice by its model-config key (``key =
"model.camera.diaphragm.n_blades"``); :func:`config_key_to_path` gives the path that
replaces it. The tables below are the only place that knows how a kind's config tables
are named in its built model.

**Example:**

```python
config_key_to_path("camera", "model.camera.diaphragm.n_blades")
# 'model.aperture.diaphragm.n_blades'
path_to_config_key("eye", "model.aperture.particles[1].n_max")
# 'model.eye.particles.1.n_max'
```
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

from invglare.errors import ConfigError

#: Per model kind, (model config prefix, parameter path prefix) pairs, the longest first.
#: Keys outside these prefixes are spelt the same in both (``model.luminance_scale``).
PREFIXES: dict[str, tuple[tuple[str, str], ...]] = {
    "aperture": (("model.shapes", "model.aperture.shapes"),),
    "eye": (
        ("model.eye.lashes_upper", "model.aperture.upper_lashes"),
        ("model.eye.lashes_lower", "model.aperture.lower_lashes"),
        ("model.eye", "model.aperture"),
    ),
    "camera": (
        ("model.camera.cross_screen", "model.aperture.filter"),
        ("model.camera", "model.aperture"),
    ),
    "temporal": (
        ("model.eye.lashes_upper", "model.aperture.upper_lashes"),
        ("model.eye.lashes_lower", "model.aperture.lower_lashes"),
        ("model.eye", "model.aperture"),
    ),
    "veiling": (("model.lens", "model.ghosts.lens"),),
}

_DOT_INDEX = re.compile(r"\.(\d+)(?=\.|$)")
_BRACKET_INDEX = re.compile(r"\[(\d+)\]")


def _swap_prefix(text: str, pairs: tuple[tuple[str, str], ...], forward: bool) -> str:
    for config_prefix, path_prefix in pairs:
        old, new = (config_prefix, path_prefix) if forward else (path_prefix, config_prefix)
        if text == old or text.startswith(old + "."):
            return new + text[len(old) :]
    return text


def config_key_to_path(kind: str, key: str) -> str:
    """The parameter path of a dotted model-config `key` of a model of `kind`.

    List positions (``particles.1``) become indices (``particles[1]``); a kind this
    module does not know keeps its keys as they are.
    """
    dotted = _swap_prefix(key, PREFIXES.get(kind, ()), forward=True)
    return _DOT_INDEX.sub(r"[\1]", dotted)


def path_to_config_key(kind: str, path: str) -> str:
    """The dotted model-config key of a parameter `path` (the inverse of
    :func:`config_key_to_path`): indices become list positions."""
    dotted = _BRACKET_INDEX.sub(r".\1", path.replace(" ", ""))
    return _swap_prefix(dotted, PREFIXES.get(kind, ()), forward=False)


def _step(node: Any, part: str) -> Any:
    """One step of a dotted config key: a table key, or a list index (``shapes.0``)."""
    if isinstance(node, Mapping) and part in node:
        return node[part]
    if isinstance(node, list) and part.isdigit() and int(part) < len(node):
        return node[int(part)]
    raise KeyError(part)


def get_key(config: Mapping[str, Any], key: str, where: str, hint: str = "") -> Any:
    """The value at the dotted `key` of a parsed model `config`.

    **Raises:** :class:`~invglare.errors.ConfigError` naming `where`, the key and the
    step it stopped at (with `hint` appended).
    """
    node: Any = config
    for part in key.split("."):
        try:
            node = _step(node, part)
        except KeyError:
            raise ConfigError(
                f"{where}: the model config has no key {key!r} (stopped at {part!r}){hint}"
            ) from None
    return node


def set_key(config: dict[str, Any], key: str, value: Any) -> None:
    """Write `value` at the dotted `key` of a parsed model `config` (its table must exist)."""
    parts = key.split(".")
    node: Any = config
    for part in parts[:-1]:
        node = _step(node, part)
    if isinstance(node, list):
        node[int(parts[-1])] = value
    else:
        node[parts[-1]] = value
