"""A forward model specialised to a fit: work the free parameters cannot change is dropped.

A model and observation built from configs must serve any fit. A fit knows its free
parameters and their bounds, and :func:`specialise_forward` uses that, without changing
any value:

- **stamp windows** (:func:`fit_stamp_windows`): a model built from a config fixes its
  eye's stamp windows with room to spare (1.5 times the elements' current half-extent,
  :meth:`~invglare.aperture.eye.EyeAperture.with_stamp_windows`). Sized for the bounds
  (the model's ``sized_for``) instead, they are smaller: a stamped element costs its
  window's area, and in a daylight eye the lash stamps are most of an evaluation. A
  window only sets which pixels an element is evaluated on, and every pixel the element
  reaches stays inside it.
- **identity geometry** (:meth:`~invglare.fit.Observation.with_fixed_geometry`): a
  rescaling by exactly 1 and a rotation by exactly 0 that no parameter changes are
  skipped.
"""

from __future__ import annotations

import itertools
import math

import equinox as eqx
import jax
import numpy as np

from invglare.errors import InvglareError
from invglare.fit.observation import Forward
from invglare.fit.params import ParameterSpace
from invglare.models.base import AbstractGlareModel

#: At most this many free model parameters are bounded by their box's corners (2**n
#: evaluations of the element sizes); with more, the model's own windows are kept.
MAX_CORNER_PARAMETERS = 8


def specialise_forward(space: ParameterSpace, forward: Forward) -> Forward:
    """`forward` with the stamp windows and the observation's geometry fitted to `space`.

    Called by :func:`~invglare.fit.make_residual_fn` and
    :func:`~invglare.fit.sample.make_log_posterior`; predictions are unchanged.
    """
    forward = fit_stamp_windows(space, forward)
    free_obs = {p.steps[1] for p in space.all if p.steps[0] == "obs" and len(p.steps) > 1}
    return eqx.tree_at(lambda f: f.obs, forward, forward.obs.with_fixed_geometry(free_obs))


def fit_stamp_windows(space: ParameterSpace, forward: Forward) -> Forward:
    """`forward` with its model's static raster structure just large enough for the box.

    The elements' sizes grow monotonically with each size parameter (lengths, thicknesses,
    radii, their spreads, a lash's curvature in absolute value), so the largest element
    over the box of bounds is found at one of its corners: the model is asked
    (:meth:`~invglare.models.base.AbstractGlareModel.sized_for`) for a copy sized for
    itself at every corner, with no extra headroom.

    `forward` comes back unchanged where this cannot be decided: a model that does not
    implement the model interface, no free model parameter,
    more than :data:`MAX_CORNER_PARAMETERS` of them, an infinite bound, traced values, or
    a corner the model refuses.
    """
    if not isinstance(forward.model, AbstractGlareModel):
        return forward  # a plain callable model (a user's own Module) has no raster to size
    leaves = jax.tree_util.tree_leaves(eqx.filter(forward, eqx.is_array))
    if any(isinstance(leaf, jax.core.Tracer) for leaf in leaves):
        return forward
    sized = [i for i, p in enumerate(space.all) if p.steps[0] == "model"]
    if not sized or len(sized) > MAX_CORNER_PARAMETERS:
        return forward
    bounds = [(space.all[i].lower, space.all[i].upper) for i in sized]
    if not all(math.isfinite(v) for pair in bounds for v in pair):
        return forward
    base = np.asarray([p.init for p in space.all], dtype=float)
    corners = []
    try:
        for corner in itertools.product(*bounds):
            values = base.copy()
            values[sized] = corner
            corners.append(space.apply(forward, values).model)
        fitted = forward.model.sized_for(corners)
    except InvglareError:
        return forward
    if fitted is forward.model:
        return forward
    return eqx.tree_at(lambda f: f.model, forward, fitted)
