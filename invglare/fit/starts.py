"""Where a fit starts: guesses from the photo, default initial values, starts across the bounds.

A fit config names bounds and, optionally, initial values; what it leaves out is
guessed here:

- the source's flux and background from the photo (:meth:`~invglare.fit.Observation.from_target`)
  and its centre from the bright core (:func:`centre_guess`), together :func:`photo_guesses`;
- any other initial value from the model as built (:func:`default_init`);
- the starts of a multi-start fit as a Latin hypercube across the bounds, with
  parameters that have an init range drawn stratified within it (:func:`draw_starts`).

**Example:**

```python
guesses = photo_guesses(photo, obs)                  # {"obs.flux": ..., "obs.dx_px": ...}
init = default_init(forward, "obs.flux", 0.0, math.inf, guesses)
starts = draw_starts(space, {0: (2.5, 4.0)}, n=3, seed=0)    # (3, p) physical values
```
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import jax
import numpy as np
from jaxtyping import ArrayLike, Float

from invglare.fit.params import ParameterSpace
from invglare.fit.paths import read_path

#: A guess on or outside finite bounds is moved this fraction of the width inside them.
GUESS_MARGIN = 0.01


def centre_guess(
    target: Float[ArrayLike, "h w"], background: float = 0.0, radius_px: float = 12.0
) -> dict[str, float]:
    """``{"obs.dx_px", "obs.dy_px"}``: the source centre from the photo's bright core.

    The centroid (above background) of the pixels within `radius_px` of pixel
    ``(w // 2, h // 2)`` that are brighter than half the peak there, relative to that
    pixel: for a clipped core it is the clipped disk's centre (bright features farther
    out, such as a filter's diffraction orders, are left out). A start within a pixel of
    the truth keeps the centre out of the other parameters' way.

    **Arguments:**

    - `target`: the photo in counts, ``(h, w)``.
    - `background`: counts per pixel to subtract first.
    - `radius_px`: how far from the centre pixel the core is looked for.

    **Returns:** the offsets in pixels, or ``{}`` when nothing there rises above the
    background.

    **Example:** ``centre_guess(photo, 20.0)``, e.g. ``{"obs.dx_px": 0.31, "obs.dy_px": -0.2}``.
    """
    t = np.asarray(target, dtype=np.float64) - background
    h, wd = t.shape
    rows, cols = np.indices(t.shape)
    near = (rows - h // 2) ** 2 + (cols - wd // 2) ** 2 <= radius_px**2
    peak = t[near].max()
    if not peak > 0:
        return {}
    w = np.where(near & (t >= 0.5 * peak), t, 0.0)
    total = w.sum()
    return {
        "obs.dx_px": float((w * cols).sum() / total - wd // 2),
        "obs.dy_px": float((w * rows).sum() / total - h // 2),
    }


def photo_guesses(target: Float[ArrayLike, "h w"], obs: Any) -> dict[str, float]:
    """Initial values the photo suggests: flux and background of `obs`, the core's centre.

    **Arguments:**

    - `target`: the photo in counts, ``(h, w)``.
    - `obs`: the :class:`~invglare.fit.Observation` guessed from it
      (:meth:`~invglare.fit.Observation.from_target`).

    **Returns:** ``{path: value}`` for ``obs.flux``, ``obs.background`` and, where the
    core is found, ``obs.dx_px`` and ``obs.dy_px``.

    **Example:** ``photo_guesses(photo, Observation.from_target(photo, gain=2.0))``.
    """
    guesses = {"obs.flux": float(obs.flux), "obs.background": float(obs.background)}
    guesses.update(centre_guess(target, float(obs.background)))
    return guesses


def default_init(
    forward: Any, path: str, lower: float, upper: float, guesses: Mapping[str, float]
) -> float:
    """The initial value of a free parameter whose config gives none.

    A guess from the photo (`guesses`, see :func:`photo_guesses`) where there is one,
    moved :data:`GUESS_MARGIN` of the width inside finite bounds (a guess on a bound
    would be an invalid start); otherwise the value `forward` holds at `path`, or the
    middle of finite bounds when that value lies outside them.

    **Example:** ``default_init(forward, "model.aperture.pupil.diameter_mm", 2.0, 4.5, {})``
    is the model config's diameter (3.0).
    """
    finite = math.isfinite(lower) and math.isfinite(upper)
    if path in guesses:
        init = float(guesses[path])
        if finite:
            margin = GUESS_MARGIN * (upper - lower)
            init = min(max(init, lower + margin), upper - margin)
        return init
    init = read_path(forward, path)
    if not (lower < init < upper) and finite:
        init = 0.5 * (lower + upper)
    return init


def draw_starts(
    space: ParameterSpace, ranges: Mapping[int, tuple[float, float]], n: int, seed: int
) -> Float[np.ndarray, "n p"]:
    """`n` physical starts across the bounds (a Latin hypercube, nuisances at their init).

    **Arguments:**

    - `space`: the free parameters (see :meth:`~invglare.fit.ParameterSpace.sample_starts`
      for how the bounds are covered).
    - `ranges`: ``{column: (low, high)}``: parameters drawn stratified within an init
      range instead.
    - `n`, `seed`: how many starts, and the key they are drawn with.

    **Returns:** ``(n, p)`` float64 values in the order of `space.paths`; the same
    `seed` gives the same starts.

    **Example:** ``draw_starts(space, {}, 3, seed=0)``.
    """
    key_bounds, key_ranges = jax.random.split(jax.random.key(seed))
    starts = np.array(space.from_latent(space.sample_starts(key_bounds, n)), dtype=np.float64)
    rng = np.random.default_rng(np.asarray(jax.random.key_data(key_ranges)))
    for col, (lo, hi) in ranges.items():
        u = (rng.permutation(n) + rng.uniform(size=n)) / n
        starts[:, col] = lo + (hi - lo) * u
    return starts
