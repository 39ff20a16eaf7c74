"""The layout of a row of eyelashes: each lash's root, direction, length, width and bend.

A row of :class:`~invglare.aperture.eye.Eyelashes` draws its lashes from a key (a
relaxed-count pool). A real eye has no key: a fit of a photo frees each lash that the
photo resolves as parameters of its own. :class:`LashLayout` holds those per-lash
values, one entry per element of the pool; a row that carries a layout draws nothing
and its population parameters (count, mean angle, spread, mean length, ...) no longer
place the lashes: they are the parameters of the distribution the lashes were drawn
from, and :func:`layout_prior_terms` says how likely the layout is under them (the
hierarchical prior a fit ties the per-lash leaves to the population with).

The generative model (what :meth:`Eyelashes.drawn_layout` draws) and the prior it
implies, for lash ``i`` of a row of `count` lashes with slots ``s = root_span / count``
apart:

- `root_mm`: drawn ``(i + 1/2) s - span / 2 + jitter s (u - 1/2)``; prior mean the slot,
  sd ``jitter s / sqrt(12)``;
- `angle_deg`: drawn ``mean_angle + spread z``; prior ``N(mean_angle, spread)`` (exact);
- `length_mm`: drawn ``length (1 + length_spread (2u - 1))``; prior mean `length`, sd
  ``length length_spread / sqrt(3)``;
- `thickness_mm`: drawn as the length with `thickness_spread`; prior mean `thickness`, sd
  ``thickness thickness_spread / sqrt(3)``;
- `curvature_per_mm`: drawn as the row's; prior ``N(curvature, CURVATURE_SD_PER_MM)``.

(``u ~ U(0, 1)``, ``z ~ N(0, 1)``.) The uniform draws are given the normal prior of the
same mean and variance: smooth, as a least-squares fit needs; each standard deviation is
kept above a floor (:data:`MIN_SD`) so that a spread of 0 stays a finite prior.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from invglare._core.checks import as_float
from invglare.aperture._checks import check_finite
from invglare.errors import ConfigError

#: The per-lash leaves of a layout, in the order of the fields.
LAYOUT_LEAVES = ("root_mm", "angle_deg", "length_mm", "thickness_mm", "curvature_per_mm")

#: Floor of each prior standard deviation (in the leaf's unit), so that a population
#: spread of 0 (every lash alike) is a narrow prior instead of an infinitely narrow one.
MIN_SD = {
    "root_mm": 1e-3,
    "angle_deg": 0.05,
    "length_mm": 1e-3,
    "thickness_mm": 1e-4,
    "curvature_per_mm": 1e-4,
}

#: Default prior standard deviation (1/mm) of a lash's curvature about the row's: the
#: generative model bends every lash alike, a real row does not.
CURVATURE_SD_PER_MM = 0.05


class LashLayout(eqx.Module):
    """Per-lash values of a row of eyelashes, one entry per element of the pool.

    **Arguments** (each a 1-D array of length ``n_max``):

    - `root_mm`: where the lash is rooted, as the position along the lid margin (mm,
      the margin's own x, 0 at its apex).
    - `angle_deg`: its direction relative to the margin's normal into the opening
      (deg, counter-clockwise positive), as the row's `mean_angle_deg`.
    - `length_mm`, `thickness_mm`: its length and width (mm, > 0).
    - `curvature_per_mm`: its signed curvature (1/mm).

    Lash ``i`` keeps its relaxed-count weight ``smooth_step(count - i)``.

    **Example:** ``layout = lashes.drawn_layout()``, then
    ``eqx.tree_at(lambda l: l.angle_deg, layout, layout.angle_deg.at[3].set(5.0))``.
    """

    root_mm: Float[Array, " n"] = eqx.field(converter=as_float)
    angle_deg: Float[Array, " n"] = eqx.field(converter=as_float)
    length_mm: Float[Array, " n"] = eqx.field(converter=as_float)
    thickness_mm: Float[Array, " n"] = eqx.field(converter=as_float)
    curvature_per_mm: Float[Array, " n"] = eqx.field(converter=as_float)

    def __check_init__(self):
        n = self.root_mm.shape
        if len(n) != 1:
            raise ConfigError(f"lash layout root_mm must be a 1-D array, got shape {n}")
        for name in LAYOUT_LEAVES:
            check_finite(f"lash layout {name}", getattr(self, name), n)

    @property
    def size(self) -> int:
        """Number of lashes the layout describes."""
        return int(self.root_mm.shape[0])


def slot_positions(
    count: Float[Array, ""], span_mm: Float[Array, ""], n: int, dtype
) -> tuple[Float[Array, " n"], Float[Array, ""]]:
    """The lashes' slot centres along the margin (mm) and the slot width ``span / count``."""
    spacing = span_mm / jnp.maximum(count, 1.0)
    i = jnp.arange(n, dtype=dtype)
    return (i + 0.5) * spacing - 0.5 * span_mm, spacing


def prior_moments(lashes) -> dict[str, tuple[Array, Array]]:
    """``{leaf: (mean, sd)}`` of every lash's prior under the row's population parameters.

    Means and standard deviations are arrays of length ``n_max`` (see the module table);
    `lashes` is an :class:`~invglare.aperture.eye.Eyelashes`.
    """
    dtype = jnp.result_type(lashes.length_mm, lashes.mean_angle_deg, float)
    n = lashes.n_max
    slots, spacing = slot_positions(lashes.count, lashes.root_span_mm, n, dtype)
    ones = jnp.ones(n, dtype)
    sd12, sd3 = 1.0 / math.sqrt(12.0), 1.0 / math.sqrt(3.0)
    raw = {
        "root_mm": (slots, lashes.spacing_jitter * spacing * sd12 * ones),
        "angle_deg": (lashes.mean_angle_deg * ones, lashes.angular_spread_deg * ones),
        "length_mm": (
            lashes.length_mm * ones,
            lashes.length_mm * lashes.length_spread * sd3 * ones,
        ),
        "thickness_mm": (
            lashes.thickness_mm * ones,
            lashes.thickness_mm * lashes.thickness_spread * sd3 * ones,
        ),
        "curvature_per_mm": (lashes.curvature_per_mm * ones, CURVATURE_SD_PER_MM * ones),
    }
    return {k: (m, jnp.sqrt(s * s + MIN_SD[k] ** 2)) for k, (m, s) in raw.items()}


def layout_prior_terms(
    lashes, leaf: str, index: Array
) -> tuple[Float[Array, " k"], Float[Array, " k"]]:
    """Standardised deviations ``(x - mean) / sd`` and ``log sd`` of the lashes `index`.

    For the `leaf` of the layout of `lashes` (which must carry one). The log prior of
    those entries is ``-sum(z**2) / 2 - sum(log sd) - k log(2 pi) / 2``.
    """
    if lashes.layout is None:
        raise ConfigError(f"{lashes.owner} have no layout: there is no per-lash prior to take")
    if leaf not in LAYOUT_LEAVES:
        raise ConfigError(f"unknown lash layout leaf {leaf!r}; valid: {', '.join(LAYOUT_LEAVES)}")
    mean, sd = prior_moments(lashes)[leaf]
    x = getattr(lashes.layout, leaf)[index]
    return (x - mean[index]) / sd[index], jnp.log(sd[index])
