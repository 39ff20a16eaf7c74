"""Checks of parameter values shared by the eye and the camera (on top of `_core.checks`)."""

from __future__ import annotations

import numpy as np

from invglare._core.checks import is_concrete, shown
from invglare.errors import PhysicsRangeError


def check_finite(name: str, value, shape: tuple[int, ...] | None = None) -> None:
    """Raise :class:`PhysicsRangeError` unless a concrete `value` is finite (with `shape`).

    **Arguments:**

    - `name`: the parameter, as the message should name it (e.g. ``"pupil rotation_deg"``).
    - `value`: the value; a traced one (inside `jit` / `grad` / `vmap`) is not checked.
    - `shape`: the shape it must have, or None for any.
    """
    if not is_concrete(value):
        return
    arr = np.asarray(value, dtype=float)
    if shape is not None and arr.shape != tuple(shape):
        raise PhysicsRangeError(f"{name} must have shape {tuple(shape)}, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise PhysicsRangeError(f"{name} must be finite, got {shown(arr)}")
