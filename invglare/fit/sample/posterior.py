"""The log posterior a chain samples: likelihood, priors and the latent transform's Jacobian.

emcee walks in the *latent* space of the :class:`~invglare.fit.ParameterSpace`, so the
density is the physical posterior times the Jacobian of the transform (see
:mod:`invglare.fit.sample`); :func:`make_log_posterior` builds it for one walker,
checking the space, priors, target and options first.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from collections.abc import Mapping
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int
from scipy.special import ndtr

from invglare.errors import ConfigError
from invglare.fit.draw_scatter import scatter_options
from invglare.fit.lash_prior import joint_log_prior, layout_priors
from invglare.fit.observation import CENSORING, Forward, check_target
from invglare.fit.params import ParameterSpace
from invglare.fit.specialise import specialise_forward
from invglare.fit.views import ResidualFn, make_residual_fn

#: The space emcee walks in (see :mod:`invglare.fit.sample.run`).
SAMPLING_SPACE = "latent"

LIKELIHOODS = ("pixels", "views")

#: A prior holding less than this fraction of its probability inside the bounds is refused.
MIN_PRIOR_MASS = 1e-12


def prior_mass(space: ParameterSpace) -> dict[str, float]:
    """Fraction of each parameter's prior probability that lies inside its bounds.

    Uniform priors count as 1 (they are the bounds). ``normal``:
    ``Phi((upper - mean) / std) - Phi((lower - mean) / std)``; ``lognormal``: the
    same in ``log x`` with ``log(max(lower, 0))``.

    **Example:** a ``("normal", 10.0, 0.5)`` prior on a parameter bounded to
    ``[2, 5]`` has mass ``~1e-23`` inside: the prior and the bounds disagree.
    """
    out = {}
    for p in space.all:
        prior = p.prior
        if prior is None or prior.kind == "uniform":
            out[p.path] = 1.0
            continue
        lo, hi = p.lower, p.upper
        if prior.kind == "lognormal":
            if hi <= 0:
                out[p.path] = 0.0
                continue
            lo = math.log(lo) if lo > 0 else -math.inf
            hi = math.log(hi) if math.isfinite(hi) else math.inf
        a = (lo - prior.mean) / prior.std
        b = (hi - prior.mean) / prior.std
        # Subtract in the tail where the difference keeps its digits.
        mass = float(ndtr(b) - ndtr(a)) if a < 0 else float(ndtr(-a) - ndtr(-b))
        out[p.path] = max(mass, 0.0)
    return out


def check_priors(space: ParameterSpace) -> None:
    """Refuse priors that put (essentially) no probability inside their parameter's bounds.

    Raises :class:`~invglare.errors.ConfigError` naming the parameter, its prior,
    its bounds and the mass inside (below :data:`MIN_PRIOR_MASS`).
    """
    for p in space.all:
        mass = prior_mass(space)[p.path]
        if mass < MIN_PRIOR_MASS:
            pr = p.prior
            raise ConfigError(
                f"the {pr.kind}(mean={pr.mean:g}, std={pr.std:g}) prior of {p.path!r} puts "
                f"{mass:.1e} of its probability inside the bounds [{p.lower:g}, {p.upper:g}]: "
                "the prior and the bounds contradict each other (a lognormal's mean is of "
                "log x); fix the prior's mean / std or the bounds"
            )


class LogPosterior(eqx.Module):
    """The log posterior density of the latent vector of a fit, for one walker.

    ``lp(z) = log L(target | x(z)) + log prior(x(z)) + log |det dx/dz|``: its samples
    in `z` map to physical samples ``x(z)`` of the posterior (see :mod:`invglare.fit.sample.run`).
    Call it on one latent vector; `jax.vmap` it over walkers.

    Build it with :func:`make_log_posterior`.
    """

    space: ParameterSpace = eqx.field(static=True)
    forward: Forward
    target: Float[Array, "h w"]
    mask: Bool[Array, "h w"] | None
    residual_fn: ResidualFn | None
    #: Flat indices of the target's saturated pixels in use (see `Observation.log_likelihood`).
    censored: Int[Array, " k"] | None
    censoring: str = eqx.field(static=True, default="survival")
    likelihood: str = eqx.field(static=True, default="pixels")
    residual_scale: float = eqx.field(static=True, default=1.0)
    #: Joint priors of the free parameters (a fitted eyelash layout's, invglare.fit.lash_prior).
    priors: tuple = ()

    def log_likelihood(self, latent: Float[Array, " p"]) -> Float[Array, ""]:
        """The log-likelihood at latent `latent` (see :mod:`invglare.fit.sample.run`)."""
        if self.likelihood == "views":
            r = self.residual_fn(latent, None)
            return -0.5 * jnp.sum(r * r) / self.residual_scale
        fwd = self.space.apply(self.forward, self.space.from_latent(latent))
        expected = fwd.expected()
        return fwd.obs.log_likelihood(
            self.target, expected, censoring=self.censoring, mask=self.mask, censored=self.censored
        )

    def log_prior(self, latent: Float[Array, " p"]) -> Float[Array, ""]:
        """Log prior of the physical values plus the log-Jacobian of the latent transform."""
        x = self.space.from_latent(latent)
        joint = joint_log_prior(self.priors, self.space.apply(self.forward, x))
        return self.space.log_prior(x) + self.space.log_det_jacobian(latent) + joint

    def __call__(self, latent: Float[Array, " p"]) -> Float[Array, ""]:
        prior = self.log_prior(latent)
        # Outside the prior's support the model may not even be defined (a negative
        # diameter): -inf, whatever the likelihood says there.
        ok = jnp.isfinite(prior)
        return jnp.where(ok, prior + self.log_likelihood(latent), -jnp.inf)


def make_log_posterior(
    space: ParameterSpace,
    forward_template: Forward,
    target: Float[ArrayLike, "h w"],
    *,
    likelihood: str = "pixels",
    censoring: str = "survival",
    mask: Bool[ArrayLike, "h w"] | None = None,
    views: Mapping[str, float] | None = None,
    view_options: Mapping[str, Mapping[str, Any]] | None = None,
    residual_scale: float = 1.0,
    scatter_at: Mapping[str, float] | None = None,
) -> LogPosterior:
    """Build the log posterior of a fit, validating the space, priors, target and options.

    **Arguments:**

    - `space`, `forward_template`, `target`: as for :func:`invglare.fit.fit`.
    - `likelihood`: ``"pixels"`` (Poisson–Gaussian, the default) or ``"views"``
      (Gaussian on the fit's residuals; needs `views`, optionally `view_options`,
      and `residual_scale`, the fit's `covariance_scale`). Statistics views that ask for
      ``draws`` are whitened by the scatter between eyes measured at `scatter_at` (the
      fit's values, ``{path: value}``; see :mod:`invglare.fit.draw_scatter`).
    - `censoring`: how saturated pixels enter the pixel likelihood (``"survival"``
      or ``"exclude"``, see :meth:`~invglare.fit.Observation.log_likelihood`).
    - `mask`: pixels to use (True), e.g. to drop hot pixels.

    **Returns:** a :class:`LogPosterior`.

    **Example:**

    ```python
    lp = make_log_posterior(space, Forward(model, obs), photo)
    lp(space.initial_latent())            # one walker
    jax.vmap(lp)(walkers)                 # many
    ```
    """
    if likelihood not in LIKELIHOODS:
        raise ConfigError(f"likelihood {likelihood!r} is not one of {', '.join(LIKELIHOODS)}")
    if censoring not in CENSORING:
        raise ConfigError(f"censoring {censoring!r} is not one of {', '.join(CENSORING)}")
    if not isinstance(forward_template, Forward):
        raise ConfigError(
            f"forward_template must be a Forward(model, obs), got {type(forward_template).__name__}"
        )
    space.check(forward_template)
    forward_template = specialise_forward(space, forward_template)
    check_priors(space)
    if not (math.isfinite(residual_scale) and residual_scale > 0):
        raise ConfigError(f"residual_scale must be finite and > 0, got {residual_scale!r}")
    out_shape = eqx.filter_eval_shape(forward_template).shape
    tgt = check_target(target, shape=out_shape, saturation=forward_template.obs.saturation)
    residual_fn = None
    if likelihood == "views":
        if not views:
            raise ConfigError("likelihood='views' needs the fit's views, e.g. {'radial': 1.0}")
        residual_fn = make_residual_fn(
            space, forward_template, tgt, views, view_options=view_options
        )
        if scatter_at is not None and any(o.get("draws", 0) for o in (view_options or {}).values()):
            latent = space.to_latent(scatter_at)
            options = scatter_options(residual_fn, latent, view_options)
            residual_fn = make_residual_fn(
                space, forward_template, tgt, views, view_options=options
            )
        # A lash layout's prior is in log_prior, once.
        residual_fn = dataclasses.replace(residual_fn, priors=())
    m = None
    if mask is not None:
        m = jnp.asarray(mask, bool)
        if m.shape != tuple(out_shape):
            raise ConfigError(f"mask has shape {m.shape}, expected the photo's {tuple(out_shape)}")
    return LogPosterior(
        space=space,
        forward=forward_template,
        target=_float64(tgt),
        mask=m,
        residual_fn=residual_fn,
        censored=jnp.asarray(forward_template.obs.censored_indices(tgt, m), jnp.int32),
        censoring=censoring,
        likelihood=likelihood,
        residual_scale=float(residual_scale),
        priors=layout_priors(space, forward_template),
    )


def _float64(a) -> Array:
    with jax.enable_x64(True):
        return jnp.asarray(a, dtype=jnp.float64)


def fingerprint(log_posterior: LogPosterior) -> str:
    """A short hash of the data and fixed values a log posterior is made of.

    Stored with a chain so that resuming it against another photo, another fixed
    value or another likelihood setting is refused: its steps would not be draws
    from the new posterior.
    """
    h = hashlib.sha256()
    h.update(f"{log_posterior.likelihood}|{log_posterior.censoring}|".encode())
    h.update("|".join(log_posterior.space.paths).encode())
    # The censored indices follow from the target, mask and clip level: not hashed, so
    # that chains stored before they existed keep their fingerprint.
    data = eqx.tree_at(lambda lp: lp.censored, log_posterior, None, is_leaf=lambda x: x is None)
    for leaf in jax.tree_util.tree_leaves(eqx.filter(data, eqx.is_array)):
        if jax.dtypes.issubdtype(leaf.dtype, jax.dtypes.prng_key):  # a model's random draw
            leaf = jax.random.key_data(leaf)
        a = np.ascontiguousarray(np.asarray(leaf))
        h.update(f"{a.dtype}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]
