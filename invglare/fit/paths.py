"""Parameter paths: naming one scalar of a model, in one language.

A fit never looks inside a model. It addresses each free parameter by a dotted
*path* into the pytree it fits, the ``Forward(model, obs)``
(``"model.aperture.shapes[0].diameter_mm"``, ``"obs.flux"``,
``"model.spectrum.wavelengths_nm[0]"``). :func:`parse_path` splits one into steps,
:func:`resolve_path` checks it against a model (listing the valid paths,
:func:`valid_paths`, when it does not exist), :func:`read_path` reads the value there
and :func:`static_int` an integer choice (a static field, such as ``n_blades``).

**One path language.** Paths are the one way a value of a model is named: in Python,
in a fit config's ``[[free]]``, ``[[discrete]]`` and ``[[stage]].fixed``, in a synth
spec's ``[set]`` (configs spell model-config keys this way too, see
:mod:`invglare.config.paths`). A part that models store under different field names
has one name in a path (:data:`FIELD_ALIASES`): a model's aperture is ``aperture`` in
every model, so the pupil is ``model.aperture.pupil.diameter_mm`` in a Kakimoto eye and
in the temporal eye (whose field is ``eye``). The older spelling ``model.eye.…`` of the
temporal eye still works, with a :class:`DeprecationWarning` naming the new one, once
per spelling; :func:`spelling` gives a path's new spelling.

**Example:**

```python
parse_path("aperture.shapes[0].center_mm[1]")     # ("aperture", "shapes", 0, "center_mm", 1)
read_path(forward, "model.aperture.pupil.diameter_mm")   # 3.0
```
"""

from __future__ import annotations

import dataclasses
import difflib
import re
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from invglare.errors import ConfigError

_TOKEN = re.compile(r"\.?([A-Za-z_][A-Za-z_0-9]*)|\[\s*(-?\d+(?:\s*,\s*-?\d+)*)\s*\]")

#: The name a path gives a part of a model, and the other field names models store it
#: under. A path naming the part by one of those (``model.eye.…`` for the temporal
#: model's aperture) is the older spelling: it still resolves, with a DeprecationWarning.
FIELD_ALIASES: dict[str, tuple[str, ...]] = {"aperture": ("eye",)}
_ALIAS_OF = {alias: name for name, aliases in FIELD_ALIASES.items() for alias in aliases}

#: Old spellings already warned about (each is warned about once per process).
_WARNED: set[str] = set()


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


def path_of_steps(steps: Sequence) -> str:
    """The path text of parsed `steps` (``("shapes", 0, "diameter_mm")`` ->
    ``"shapes[0].diameter_mm"``): one text per value, whatever the spacing written."""
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


def vector_length(model: Any, path: str) -> int | None:
    """The length of the 1-D float array leaf `path` names as a whole, else None.

    A fit config frees such a leaf element by element (``layout.angle_deg`` of a lash
    row is ``layout.angle_deg[0]``, ``[1]``, ...). Raises
    :class:`~invglare.errors.ConfigError` (listing the valid paths) when `path` does not
    exist.
    """
    node, _, index, _ = _walk(model, path, parse_path(path))
    if not index and _is_float_array(node) and node.ndim == 1:
        return int(node.shape[0])
    return None


def read_path(model: Any, path: str) -> float:
    """The value `model` holds at the scalar `path`, as a Python float.

    **Example:** ``read_path(forward, "obs.flux")``.
    """
    steps, index = resolve_path(model, path)
    leaf = np.asarray(leaf_getter(steps)(model))
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


def leaf_getter(steps: tuple):
    """A function returning the node at `steps` (as from :func:`resolve_path`) of a tree:
    the ``where`` of :func:`equinox.tree_at`."""

    def where(tree):
        node = tree
        for s in steps:
            node = node[s] if isinstance(s, int) else getattr(node, s)
        return node

    return where
