"""Many same-size photos of one model, fitted by their likelihood in one vmapped solve.

:func:`fit_photos` is :func:`invglare.fit.fit` for a stack of photos (a calibration series,
the noise draws of a Monte-Carlo check): one start, the photos' Poisson–Gaussian likelihood
(the `pixels` view, :mod:`invglare.fit.deviance`), Levenberg–Marquardt, and the covariance
from the Fisher information at each optimum, all in one compiled call vmapped over the
photos (the model's fixed values shared).

**Example:**

```python
fits = fit_photos(space, Forward(model, obs), photos)      # photos: (n, h, w)
fits.values[:, 0], fits.stderr[:, 0]                        # the first parameter, per photo
```
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float

from invglare.errors import ConfigError, InputDataError
from invglare.fit.observation import Forward
from invglare.fit.params import ParameterSpace
from invglare.fit.solve import NOISE_PATHS, _Config, _solve_one, _status_code, jacobian_columns
from invglare.fit.views import ResidualFn, make_residual_fn


@dataclasses.dataclass
class PhotoFits:
    """Per-photo results of :func:`fit_photos` (rows are photos, columns `paths`).

    - `values`, `stderr`: ``(n, p)`` physical values and standard errors (inverse Fisher
      information; NaN where it is singular).
    - `covariance`: ``(n, p, p)``.
    - `loss`: ``(n,)`` sum of squared deviance residuals (``-2 log L`` + a constant).
    - `converged`: ``(n,)`` whether each solve ended successfully.
    """

    paths: list[str]
    values: np.ndarray
    stderr: np.ndarray
    covariance: np.ndarray
    loss: np.ndarray
    converged: np.ndarray


def solve_photos(
    fn: ResidualFn,
    latent0: Float[Array, " p"],
    targets: Float[Array, "n h w"],
    saturated: Bool[Array, "n h w"],
    *,
    max_steps: int = 256,
    rtol: float = 1e-6,
    atol: float = 1e-8,
) -> tuple[Array, Array, Array, Array]:
    """Levenberg–Marquardt of `fn`'s residuals for each photo, from one latent start.

    `fn`'s target and clip mask are replaced by each photo's; its views are used as they
    are (:func:`fit_photos` gives it the likelihood). **Returns:** ``(latent (n, p),
    loss (n,), status (n,), information (n, p, p))``: the information is ``J^T J`` of the
    likelihood's scoring form when `fn` is the likelihood, else of `fn`'s residuals.
    """
    cfg = _Config("lm", float(rtol), float(atol), int(max_steps), record=False, live=False)
    return _solve_photos(fn, jnp.asarray(latent0), targets, saturated, cfg)


@eqx.filter_jit
def _solve_photos(fn, latent0, targets, saturated, cfg):
    def one(target, sat):
        f = eqx.tree_at(lambda r: (r.target, r.saturated), fn, (target, sat))
        zero = jnp.asarray(0, jnp.int32)
        z, loss, code, *_ = _solve_one(f, latent0, zero, zero, cfg)
        jac, _ = jacobian_columns(f.information_form() if f.pure_likelihood else f, z)
        return z, loss, code, jac.T @ jac

    return jax.vmap(one)(targets, saturated)


def fit_photos(
    space: ParameterSpace,
    forward_template: Forward,
    targets: Float[ArrayLike, "n h w"],
    *,
    start: Mapping[str, float] | None = None,
    censoring: str = "survival",
    max_steps: int = 256,
    rtol: float = 1e-6,
    atol: float = 1e-8,
) -> PhotoFits:
    """Fit the free parameters of `space` to every photo of `targets` by its likelihood.

    **Arguments:**

    - `space`, `forward_template`: as for :func:`invglare.fit.fit` (the noise model's gain
      and read noise fixed).
    - `targets`: ``(n, h, w)`` photos in counts, the shape of the model's output.
    - `start`: ``{path: value}`` physical start for every photo (default: the space's
      initial values).
    - `censoring`: how clipped pixels enter (``"survival"`` or ``"exclude"``).
    - `max_steps`, `rtol`, `atol`: as for :func:`invglare.fit.fit`.

    Run it in float64 (``jax.enable_x64``). **Returns:** a :class:`PhotoFits`.
    """
    stack = np.asarray(targets)
    if stack.ndim != 3 or stack.shape[0] < 1:
        raise InputDataError(f"targets must be a stack (n, h, w) of photos, got {stack.shape}")
    if not np.all(np.isfinite(stack)):
        raise InputDataError("targets hold non-finite (NaN or inf) pixels")
    noise = [p for p in space.paths if p in NOISE_PATHS]
    if noise:
        raise ConfigError(f"{', '.join(noise)} cannot be fitted by the pixel likelihood")
    view = {"pixels": {"domain": "likelihood", "censoring": censoring}}
    # Built on the first photo (which checks the space, model and photo), then vmapped.
    fn = make_residual_fn(space, forward_template, stack[0], {"pixels": 1.0}, view_options=view)
    obs = fn.forward.obs
    dtype = fn.target.dtype
    photos = jnp.asarray(stack, dtype=dtype)
    saturated = jax.vmap(obs.saturated_mask)(photos)
    values0 = space.values_from(start) if start is not None else space.initial_values()
    latent, loss, code, info = (
        np.asarray(a)
        for a in solve_photos(
            fn, space.to_latent(values0), photos, saturated, max_steps=max_steps, rtol=rtol,
            atol=atol,
        )
    )  # fmt: skip
    values = np.asarray(space.from_latent(jnp.asarray(latent)))
    diag = np.asarray(jax.vmap(space.jacobian_diag)(jnp.asarray(latent)), dtype=np.float64)
    n, p = latent.shape
    cov = np.full((n, p, p), np.nan)
    for i in range(n):
        try:
            cz = np.linalg.inv(info[i].astype(np.float64))
        except np.linalg.LinAlgError:
            continue
        cov[i] = diag[i][:, None] * cz * diag[i][None, :]
    d = np.diagonal(cov, axis1=1, axis2=2)
    stderr = np.sqrt(np.where(d >= 0, d, np.nan))
    success = int(_status_code(optx.RESULTS.successful))
    return PhotoFits(
        paths=list(space.paths),
        values=values,
        stderr=stderr,
        covariance=cov,
        loss=loss,
        converged=(code == success) & np.isfinite(loss),
    )

