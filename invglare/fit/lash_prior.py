"""The hierarchical prior of a fitted eyelash layout: per-lash leaves tied to their population.

A fit that frees a lash's own values (``model.aperture.upper_lashes.layout.angle_deg[7]``,
see :class:`~invglare.aperture.eye.lash_layout.LashLayout`) gives each such leaf the
prior the row's generative model implies (the table of :mod:`~invglare.aperture.eye.lash_layout`):
the lash's root about its slot (which depends on the row's `count`), its direction about
the row's `mean_angle_deg` with sd `angular_spread_deg`, its length and width about the
row's. The population parameters, free or fixed, are read from the model being
evaluated, so a free `count`, `mean_angle_deg` or `angular_spread_deg` is fitted by its
lashes: its standard error is that of a population estimated from the lashes the photo
shows, not that of a seed. Lashes whose leaves are not free do not enter the prior (their
values were not measured).

The prior is automatic: every free layout leaf carries it. In a least-squares fit it is
a block of residuals (:meth:`LayoutPrior.residuals`): the standardised deviations
``z = (x - mean) / sd`` and one more, ``sqrt(2 sum log(sd / floor))``, whose square is
the prior's normalisation (it is what keeps a free spread from growing without bound;
``floor`` is :data:`~invglare.aperture.eye.lash_layout.MIN_SD`, so the root is real).
Its sum of squares is ``-2 log prior`` up to a constant. A sampler adds
:meth:`LayoutPrior.log_density`.

**Example:**

```python
priors = layout_priors(space, forward)         # one LayoutPrior per row with free leaves
r = prior_residuals(priors, space.apply(forward, values))
```
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from invglare.aperture.eye.lash_layout import LAYOUT_LEAVES, MIN_SD, layout_prior_terms
from invglare.aperture.eye.lashes import Eyelashes
from invglare.errors import ConfigError
from invglare.fit.paths import leaf_getter, resolve_path

#: Added under the normalisation residual's square root, so that its derivative stays
#: finite when every spread sits exactly at its floor.
_TINY = 1e-12

_LAYOUT_PATH = re.compile(r"\.layout\.(" + "|".join(LAYOUT_LEAVES) + r")\[")


class LayoutPrior(eqx.Module):
    """The prior of the free layout leaves of one row of lashes (see the module docstring).

    `row` are the steps from the fitted pytree (a ``Forward``) to the
    :class:`~invglare.aperture.eye.Eyelashes`; `leaves` pairs each layout leaf with the
    indices of its free lashes. Static configuration only: the values come from the
    pytree it is called on.
    """

    row: tuple = eqx.field(static=True)
    leaves: tuple[tuple[str, tuple[int, ...]], ...] = eqx.field(static=True)

    @property
    def size(self) -> int:
        """Number of free per-lash values the prior covers."""
        return sum(len(idx) for _, idx in self.leaves)

    def _terms(self, tree: Any) -> tuple[Array, Array, Array]:
        lashes = leaf_getter(self.row)(tree)
        zs, log_sd, floor = [], [], []
        for leaf, idx in self.leaves:
            z, lsd = layout_prior_terms(lashes, leaf, jnp.asarray(idx))
            zs.append(z)
            log_sd.append(lsd)
            floor.append(jnp.full(len(idx), math.log(MIN_SD[leaf]), lsd.dtype))
        return jnp.concatenate(zs), jnp.concatenate(log_sd), jnp.concatenate(floor)

    def residuals(self, tree: Any) -> Float[Array, " k+1"]:
        """``[z..., sqrt(2 sum log(sd / floor))]``: squared and summed, ``-2 log prior``
        up to a constant."""
        z, log_sd, floor = self._terms(tree)
        norm = jnp.sqrt(2.0 * jnp.sum(log_sd - floor) + _TINY)
        return jnp.concatenate([z, norm[None]])

    def log_density(self, tree: Any) -> Float[Array, ""]:
        """The free leaves' normalised log prior, ``-sum(z**2)/2 - sum(log sd) - k log(2 pi)/2``."""
        z, log_sd, _ = self._terms(tree)
        return -0.5 * jnp.sum(z * z) - jnp.sum(log_sd) - 0.5 * z.shape[0] * math.log(2 * math.pi)


def layout_priors(space: Any, tree: Any) -> tuple[LayoutPrior, ...]:
    """One :class:`LayoutPrior` per row of lashes with free layout leaves in `space`.

    `tree` is the pytree the space's paths address (a ``Forward``); every free path of
    the form ``<row>.layout.<leaf>[i]`` is grouped by its row. Raises
    :class:`~invglare.errors.ConfigError` when such a path's row is not a row of lashes.
    """
    rows: dict[tuple, dict[str, list[int]]] = {}
    for p in space.all:
        if not _LAYOUT_PATH.search(p.path):
            continue
        steps, index = resolve_path(tree, p.path, p.steps)
        row, leaf = steps[:-2], steps[-1]
        if steps[-2] != "layout" or len(index) != 1 or leaf not in LAYOUT_LEAVES:
            continue
        if not isinstance(leaf_getter(row)(tree), Eyelashes):
            raise ConfigError(f"{p.path!r}: a layout leaf must belong to a row of eyelashes")
        rows.setdefault(row, {}).setdefault(leaf, []).append(int(index[0]))
    return tuple(
        LayoutPrior(row, tuple((leaf, tuple(sorted(idx))) for leaf, idx in leaves.items()))
        for row, leaves in rows.items()
    )


def prior_residuals(priors: Sequence[LayoutPrior], tree: Any) -> Float[Array, " n"]:
    """The residuals of every prior in `priors` at `tree`, concatenated (empty without any)."""
    if not priors:
        return jnp.zeros(0)
    return jnp.concatenate([p.residuals(tree) for p in priors])


def joint_log_prior(priors: Sequence[LayoutPrior], tree: Any) -> Float[Array, ""]:
    """The summed log density of every prior in `priors` at `tree` (0 without any)."""
    out = jnp.zeros(())
    for p in priors:
        out = out + p.log_density(tree)
    return out


def prior_size(priors: Sequence[LayoutPrior]) -> int:
    """How many residuals :func:`prior_residuals` returns."""
    return int(np.sum([p.size + 1 for p in priors]))
