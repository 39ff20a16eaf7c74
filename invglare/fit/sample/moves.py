"""emcee's moves, chosen by name with weights (``"stretch"``, ``{de = 0.8, de_snooker = 0.2}``)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import emcee

from invglare.errors import ConfigError

#: Moves selectable by name: emcee's move classes.
MOVES: dict[str, type] = {
    "stretch": emcee.moves.StretchMove,
    "de": emcee.moves.DEMove,
    "de_snooker": emcee.moves.DESnookerMove,
    "kde": emcee.moves.KDEMove,
    "walk": emcee.moves.WalkMove,
}


def parse_moves(moves: str | Mapping[str, float] | Sequence | None) -> list[tuple[str, float]]:
    """Normalise a move specification to ``[(name, weight), ...]`` with weights summing to 1.

    Accepts a name (``"stretch"``, ``"de"``, ``"de_snooker"``, ``"kde"``,
    ``"walk"``), a mapping ``{"de": 0.8, "de_snooker": 0.2}`` or a list of names
    or ``(name, weight)`` pairs. ``None`` is the stretch move.
    """
    if moves is None:
        moves = "stretch"
    if isinstance(moves, str):
        items = [(moves, 1.0)]
    elif isinstance(moves, Mapping):
        items = list(moves.items())
    elif isinstance(moves, Sequence):
        items = [(m, 1.0) if isinstance(m, str) else tuple(m) for m in moves]
    else:
        raise ConfigError(
            f"moves must be a name, a mapping name -> weight or a list, got {moves!r}"
        )
    out = []
    for item in items:
        if len(item) != 2:
            raise ConfigError(f"a move must be a name or (name, weight), got {item!r}")
        name, weight = item
        if name not in MOVES:
            raise ConfigError(f"unknown move {name!r}; valid moves: {', '.join(MOVES)}")
        try:
            w = float(weight)
        except (TypeError, ValueError):
            raise ConfigError(
                f"the weight of move {name!r} must be a number, got {weight!r}"
            ) from None
        if not (math.isfinite(w) and w > 0):
            raise ConfigError(f"the weight of move {name!r} must be finite and > 0, got {weight!r}")
        out.append((str(name), w))
    if not out:
        raise ConfigError("moves is empty; give at least one, e.g. 'stretch'")
    total = sum(w for _, w in out)
    return [(n, w / total) for n, w in out]


def emcee_moves(spec: list[tuple[str, float]]) -> list:
    return [(MOVES[name](), w) for name, w in spec]
