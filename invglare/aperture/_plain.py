"""Concrete parameter values in the plain form configuration tables hold."""

from __future__ import annotations

import numpy as np
from jaxtyping import ArrayLike


def plain(value: ArrayLike) -> float | list[float]:
    """A concrete value as a Python float (a scalar) or a flat list of floats (an array).

    What the writers of shape, eye and camera tables store, ready for TOML or JSON.

    **Example:**

    ```python
    plain(jnp.float32(0.5))     # 0.5
    plain(jnp.array([1, 2]))    # [1.0, 2.0]
    ```
    """
    arr = np.asarray(value, dtype=float)
    return float(arr) if arr.ndim == 0 else [float(v) for v in arr.ravel()]
