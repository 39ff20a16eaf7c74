"""Views of a glare photo and the residuals a fit minimises.

A *view* turns the target photo and the model's prediction into a residual
vector. Pixel views compare pixel by pixel; the others compare statistics that
do not depend on where exactly a random needle or particle landed (the
azimuthal profile, the energy per angular sector, the halo ring radius), which
is how stochastic structure is fitted. All statistics use *soft* (linear, tent)
binning, so they are continuous — and differentiable — in the image and in the
centre.

| name      | residual                                                            |
|-----------|---------------------------------------------------------------------|
| `pixels`  | per pixel, the Poisson–Gaussian likelihood's deviance residuals     |
| `log`     | per pixel, ``log(obs + c) - log(model + c)``                        |
| `radial`  | ``log(P_target + c) - log(P_model + c)`` of the radial profiles     |
| `angular` | ``n_bins * (F_target - F_model)``, F the energy fraction per sector |
| `halo`    | ring radius of the target minus that of the model, px               |

:func:`make_residual_fn` concatenates the chosen views, each multiplied by
``sqrt(weight)``, so the loss is ``sum_v weight_v * ||r_v||**2``.

The `pixels` view's residuals are those of the likelihood :mod:`invglare.fit.deviance`
describes, the one `invglare sample` samples: their sum of squares is ``-2 log L`` up to a
constant of the data, so a least-squares fit of them is the maximum-likelihood fit. Its
variance-stabilised domains (``"anscombe"``, ``"pearson"``) are kept for starts and early
stages only: their optimum is biased (the Anscombe domain puts a flat field's background
0.13 counts low at gain 2, read noise 3), so :func:`invglare.fit.fit` ends on the
likelihood whatever domain a final view names.

Centres are ``(x, y)`` in pixel index units (column, row), e.g. ``(w // 2 + dx, h // 2 + dy)``.
"""

from __future__ import annotations

import abc
import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import log_ndtr
from jaxtyping import Array, ArrayLike, Bool, Float

from invglare._core.checks import as_float, is_concrete
from invglare._core.maths import safe_sqrt
from invglare.errors import ConfigError
from invglare.fit.deviance import deviance_residuals, fisher_weight, pixel_log_likelihood_gradient
from invglare.fit.lash_prior import layout_priors, prior_residuals
from invglare.fit.observation import Forward, Observation, check_target
from invglare.fit.params import ParameterSpace
from invglare.fit.redraw import mean_prediction
from invglare.fit.specialise import specialise_forward
from invglare.fit.trend_jacobian import trend_residuals, trend_steps

PIXEL_DOMAINS = ("likelihood", "anscombe", "pearson", "log")

#: Pixel domains that stabilise the variance: for starts and early stages, never for a
#: final estimate or its errors (see the module docstring).
STABILISED_DOMAINS = ("anscombe", "pearson")

_TINY = 1e-30


# --------------------------------------------------------------------------------------
# geometry helpers


def _offsets(shape, centre, dtype):
    h, w = shape
    cx, cy = (jnp.asarray(c, dtype=dtype) for c in centre)
    x = jnp.arange(w, dtype=dtype)[None, :] - cx
    y = jnp.arange(h, dtype=dtype)[:, None] - cy
    x, y = jnp.broadcast_arrays(x, y)
    r2 = x * x + y * y
    # A pixel exactly at the centre has r = 0, where sqrt and atan2 have no derivative:
    # safe_sqrt, and `ok` for the callers' atan2, keep NaN out of the gradient there.
    ok = r2 > 0
    return x, y, safe_sqrt(r2), ok


def _dtype(image) -> Any:
    image = jnp.asarray(image)
    return image.dtype if jnp.issubdtype(image.dtype, jnp.floating) else jnp.result_type(float)


def radial_bin_radii(n_bins: int, max_radius_px: float) -> np.ndarray:
    """Radii (px) of the bin centres of :func:`radial_profile`: ``(k + 1/2) * max_radius / n``."""
    return (np.arange(n_bins) + 0.5) * (max_radius_px / n_bins)


def radial_profile(
    image: Float[ArrayLike, "h w"],
    centre: tuple[ArrayLike, ArrayLike],
    n_bins: int,
    max_radius_px: float,
) -> Float[Array, " n_bins"]:
    """Azimuthally averaged image (mean value per pixel) in `n_bins` rings out to `max_radius_px`.

    Linear binning: a pixel at radius `r` counts in bin `k` with weight
    ``max(0, 1 - |r - r_k| / dr)`` (``r_k`` the bin centres of
    :func:`radial_bin_radii`, ``dr = max_radius_px / n_bins``), and bin `k` is the
    weighted mean of the pixels. The profile is therefore continuous in the
    centre and the image, and does not depend on azimuthal structure. A bin with
    no pixel (possible only for ``dr`` below half a pixel) reads 0.

    **Example:** ``radial_profile(img, (w // 2, h // 2), 32, 32.0)`` gives 1-px rings.
    """
    image = jnp.asarray(image)
    dtype = _dtype(image)
    _, _, r, _ = _offsets(image.shape, centre, dtype)
    dr = max_radius_px / n_bins
    # Bin k's centre sits at u = k; a pixel at u shares itself between bins floor(u) and
    # floor(u) + 1 with weights 1 - f and f (the tent weights, two per pixel). Scatter-adds
    # keep this O(pixels): a dense (n_bins, pixels) weight matrix costs n_bins times more
    # memory and compile time, and under a Jacobian (one copy per parameter) it does not fit.
    lo, f = _tent_bins((r / dr - 0.5).reshape(-1), n_bins, periodic=False)
    values = image.reshape(-1).astype(dtype)
    num = _two_bin_sum(lo, f, values, n_bins, periodic=False)
    den = _two_bin_sum(lo, f, jnp.ones_like(values), n_bins, periodic=False)
    return jnp.where(den > 0, num / jnp.where(den > 0, den, 1.0), 0.0)


def _tent_bins(u: Array, n_bins: int, *, periodic: bool) -> tuple[Array, Array]:
    """Lower bin index (int, no gradient) and the fraction `f` towards the next bin."""
    if periodic:
        u = jnp.remainder(u, n_bins)
    lo = jnp.floor(jax.lax.stop_gradient(u))
    return lo.astype(jnp.int32), u - lo


def _two_bin_sum(lo: Array, f: Array, values: Array, n_bins: int, *, periodic: bool) -> Array:
    """``sum`` of ``(1 - f) * values`` into bin `lo` and ``f * values`` into bin ``lo + 1``."""
    if periodic:
        # remainder() can round up to exactly n_bins; that is sector 0.
        lo = jnp.where(lo >= n_bins, lo - n_bins, lo)
        hi = lo + 1
        hi = jnp.where(hi >= n_bins, hi - n_bins, hi)
    else:
        hi = lo + 1
        # Negative indices would wrap around (numpy semantics) rather than be dropped.
        lo = jnp.where(lo < 0, n_bins, lo)
        hi = jnp.where(hi < 0, n_bins, hi)
    out = jnp.zeros(n_bins, dtype=values.dtype)
    out = out.at[lo].add((1.0 - f) * values, mode="drop")
    return out.at[hi].add(f * values, mode="drop")


def _radial_window(r, r_min, r_max):
    # Linear ramps one pixel wide at both edges keep the window continuous in the centre.
    return jnp.clip(r - r_min + 0.5, 0.0, 1.0) * jnp.clip(r_max - r + 0.5, 0.0, 1.0)


def angular_bin_angles_deg(n_bins: int) -> np.ndarray:
    """Centre angles (deg) of the sectors of :func:`angular_energy`: ``360 k / n``."""
    return np.arange(n_bins) * (360.0 / n_bins)


def angular_energy(
    image: Float[ArrayLike, "h w"],
    centre: tuple[ArrayLike, ArrayLike],
    n_bins: int,
    r_min: float,
    r_max: float,
) -> Float[Array, " n_bins"]:
    """Energy (sum of pixel values) per angular sector of the annulus ``r_min <= r <= r_max``.

    Sector `k` is centred at ``360 k / n_bins`` degrees (counter-clockwise from +x
    towards +y, see :func:`angular_bin_angles_deg`); a pixel at angle ``theta``
    counts in the two nearest sectors with tent weights
    ``max(0, 1 - |theta - theta_k| / dtheta)`` (periodic), and the annulus has
    1-px linear edges. Streaks and diffraction spikes show as peaks at their
    directions.

    **Example:** ``angular_energy(img, (w // 2, h // 2), 72, 4.0, 30.0)`` (5° sectors).
    """
    image = jnp.asarray(image)
    dtype = _dtype(image)
    x, y, r, ok = _offsets(image.shape, centre, dtype)
    theta = jnp.arctan2(jnp.where(ok, y, 0.0), jnp.where(ok, x, 1.0))
    dth = 2 * math.pi / n_bins
    # Two tent weights per pixel, scatter-added (see radial_profile); sectors wrap around.
    lo, f = _tent_bins((theta / dth).reshape(-1), n_bins, periodic=True)
    weighted = (image.astype(dtype) * _radial_window(r, r_min, r_max) * ok).reshape(-1)
    return _two_bin_sum(lo, f, weighted, n_bins, periodic=True)


def halo_ring_radius(
    image: Float[ArrayLike, "h w"],
    centre: tuple[ArrayLike, ArrayLike],
    r_core: float,
    r_max: float,
    *,
    background: ArrayLike = 0.0,
    n_bins: int | None = None,
    power: float = 2.0,
) -> Float[Array, ""]:
    """Radius (px) of a halo ring: the profile-weighted mean radius beyond the core.

    With ``P`` the :func:`radial_profile` (1-px bins by default) minus
    `background`, the estimate is ``sum_k q_k r_k / sum_k q_k`` with
    ``q_k = max(P_k, 0)**power * s(r_k)``, ``s`` a window that rises from 0 to 1
    over one bin at `r_core` (to exclude the bright core) and falls at `r_max`.
    Weighting by the mean *intensity* (not the energy ``2 pi r P dr``) makes a
    symmetric ring profile give its centre radius without a ``sigma**2 / R``
    bias; `power` 2 favours the ring's peak over a slowly decaying wing.
    Differentiable in the image and the centre.
    """
    n = int(n_bins) if n_bins is not None else max(math.ceil(r_max), 1)
    image = jnp.asarray(image)
    prof = radial_profile(image, centre, n, r_max) - jnp.asarray(background, image.dtype)
    rk = jnp.asarray(radial_bin_radii(n, r_max), dtype=prof.dtype)
    dr = r_max / n
    window = jnp.clip((rk - r_core) / dr + 0.5, 0.0, 1.0)
    q = jnp.maximum(prof, 0.0) ** power * window
    total = jnp.sum(q)
    return jnp.sum(q * rk) / jnp.where(total > 0, total, 1.0)


# --------------------------------------------------------------------------------------
# pixel residuals


def box_downsample(image: Float[ArrayLike, "h w"], factor: int) -> Float[Array, "hc wc"]:
    """Sum of `factor` x `factor` blocks (flux-preserving); edges not filling a block are cut."""
    image = jnp.asarray(image)
    if factor == 1:
        return image
    h, w = image.shape
    hc, wc = h // factor, w // factor
    blocks = image[: hc * factor, : wc * factor].reshape(hc, factor, wc, factor)
    return blocks.sum(axis=(1, 3))


def generalised_anscombe(
    x: Float[ArrayLike, "*shape"], gain: ArrayLike, read_noise: ArrayLike
) -> Float[Array, "*shape"]:
    """Variance-stabilising transform of Poisson–Gaussian counts: unit variance for large counts.

    ``f(x) = (2 / a) sqrt(a x + 3/8 a**2 + s**2)`` with ``a = 1 / gain`` (counts per
    electron) and ``s = read_noise`` (counts): the generalised Anscombe transform
    (Murtagh, Starck & Bijaoui 1995). With ``gain = 1, s = 0`` it is Anscombe's
    ``2 sqrt(x + 3/8)``. Negative arguments (read noise in a dark frame) are
    clipped at 0.
    """
    x = jnp.asarray(x)
    a = 1.0 / jnp.asarray(gain, x.dtype)
    arg = a * x + 0.375 * a * a + jnp.asarray(read_noise, x.dtype) ** 2
    ok = arg > _TINY
    return (2.0 / a) * jnp.where(ok, jnp.sqrt(jnp.where(ok, arg, 1.0)), 0.0)


def pixel_residuals(
    observed: Float[ArrayLike, "h w"],
    expected: Float[ArrayLike, "h w"],
    noise: Observation,
    *,
    domain: str = "likelihood",
    floor: float | None = None,
    saturated: Bool[ArrayLike, "h w"] | None = None,
    censoring: str = "survival",
    mask: Bool[ArrayLike, "h w"] | None = None,
    read_noise_scale: float = 1.0,
    censor_level: Float[ArrayLike, "h w"] | float | None = None,
    information: bool = False,
) -> Float[Array, " n"]:
    """Per-pixel residuals of an observed photo against the unclipped mean `expected`.

    **Arguments:**

    - `observed`, `expected`: counts; `expected` is *before* clipping.
    - `noise`: the :class:`~invglare.fit.Observation` holding `gain` and `read_noise`.
    - `domain`:
      - ``"likelihood"`` (default): the deviance residuals of the Poisson–Gaussian
        likelihood (:func:`invglare.fit.deviance.deviance_residuals`): half their sum of
        squares is ``-log L`` plus a constant, so their least-squares optimum is the
        maximum-likelihood point;
      - ``"anscombe"``: ``f(o) - f(e)`` with the generalised Anscombe
        transform :func:`generalised_anscombe`, approximately N(0, 1) per pixel
        for a few counts and more; its optimum is biased (for starts only);
      - ``"pearson"``: ``(o - e) / sqrt(variance(e))`` (biased too: for starts only);
      - ``"log"``: ``log(max(o, 0) + c) - log(max(e, 0) + c)`` with ``c = floor``
        counts (required), a relative comparison that spans the decades of a glare
        profile but is not noise-normalised.
    - `saturated`: observed pixels at the clip level (True = clipped). With
      ``censoring="survival"`` each contributes ``sqrt(-2 log Phi((e - S) /
      sigma))``, the censored-likelihood term (small when the model is above
      the level, growing as it falls below); with ``"exclude"`` they give 0.
    - `mask`: pixels to use (False gives 0).
    - `read_noise_scale`: multiplies the read noise (``factor`` for block sums of
      ``factor**2`` pixels).
    - `censor_level`: the level a censored pixel is known to reach (counts; a
      scalar or per pixel); defaults to ``noise.saturation``.
    - `information`: (``"likelihood"`` only) the residuals' *scoring form*: an unclipped
      pixel's value is its score over the square root of its Fisher information,
      ``(dl/de) / sqrt(w)`` (about the deviance residual), and its derivative ``-sqrt(w)
      de``, so that for the Jacobian `J` of these, ``J^T r`` is the gradient of ``-log L``
      and ``J^T J`` the Fisher information (a clipped pixel keeps its survival residual).
      For the covariance and the optimum check of :mod:`invglare.fit.solve`.

    **Returns:** a flat vector of ``h * w`` residuals (zeros where unused).
    """
    if domain not in PIXEL_DOMAINS:
        raise ConfigError(f"pixel domain {domain!r} is not one of {', '.join(PIXEL_DOMAINS)}")
    o = jnp.asarray(observed)
    e = jnp.asarray(expected)
    dtype = jnp.result_type(o.dtype, e.dtype)
    o, e = o.astype(dtype), e.astype(dtype)
    gain = noise.gain.astype(dtype)
    read = noise.read_noise.astype(dtype) * read_noise_scale
    if information and domain != "likelihood":
        raise ConfigError(f"the information form needs the likelihood domain, got {domain!r}")
    if domain == "likelihood" and information:
        w = jax.lax.stop_gradient(fisher_weight(e, gain, read))
        score = jax.lax.stop_gradient(pixel_log_likelihood_gradient(o, e, gain, read))
        root = jnp.sqrt(w)
        # Signed like the deviance residual (about (o - e) / sigma, falling as e rises).
        r = score / root - root * (e - jax.lax.stop_gradient(e))
    elif domain == "likelihood":
        r = deviance_residuals(o, e, gain, read)
    elif domain == "anscombe":
        r = generalised_anscombe(o, gain, read) - generalised_anscombe(e, gain, read)
    elif domain == "pearson":
        var = jnp.maximum(e, 0.0) / gain + read**2
        r = (o - e) / jnp.sqrt(var + _TINY)
    else:
        if floor is None or (is_concrete(floor) and not np.all(np.asarray(floor) > 0)):
            raise ConfigError(f"the log pixel domain needs a floor > 0 counts, got {floor!r}")
        r = jnp.log(jnp.maximum(o, 0.0) + floor) - jnp.log(jnp.maximum(e, 0.0) + floor)
    use = jnp.ones(o.shape, bool) if mask is None else jnp.asarray(mask, bool)
    if censor_level is None:
        censor_level = noise.saturation
    if saturated is not None:
        sat = jnp.asarray(saturated, bool)
        if censoring == "survival" and censor_level is not None:
            sigma = jnp.sqrt(jnp.maximum(e, 0.0) / gain + read**2 + _TINY)
            v = -2.0 * log_ndtr((e - jnp.asarray(censor_level, dtype)) / sigma)
            ok = v > _TINY
            surv = jnp.where(ok, jnp.sqrt(jnp.where(ok, v, 1.0)), 0.0)
            r = jnp.where(sat, surv, r)
        else:
            use = use & ~sat
    return jnp.where(use, r, 0.0).reshape(-1)


# --------------------------------------------------------------------------------------
# views as residual makers


class ViewContext(eqx.Module):
    """What a view sees: the target and the model's prediction, on the full-resolution grid.

    `expected` is unclipped, `predicted` clipped; `centre` is the source position
    ``(x, y)`` in pixel index units; `saturated` marks clipped target pixels.
    """

    target: Float[Array, "h w"]
    saturated: Bool[Array, "h w"]
    expected: Float[Array, "h w"]
    predicted: Float[Array, "h w"]
    obs: Observation
    centre: tuple


class AbstractView(eqx.Module):
    """A residual maker: ``view(ctx) -> residual vector``. Configuration is static."""

    @abc.abstractmethod
    def __call__(self, ctx: ViewContext) -> Float[Array, " n"]:
        """Residuals of the target against the model, a 1-D vector."""

    @abc.abstractmethod
    def size(self, shape: tuple[int, int]) -> int:
        """Length of the residual vector for an image of `shape`."""


def _optional_float(x: ArrayLike | None) -> Array | None:
    return None if x is None else as_float(x)


class PixelView(AbstractView):
    """Pixel-wise residuals (see :func:`pixel_residuals`); `factor` > 1 compares block sums.

    In a coarse stage (`factor` > 1) target and model are summed over blocks
    (counts are kept) and the read noise grows by `factor`. A block holding a
    clipped pixel is censored too: its unclipped sum is at least the observed
    (clipped) sum, which gives the survival term with that sum as the level
    (``censoring="exclude"`` drops such blocks instead). Dropping them would
    throw away the core, and with it most of what a coarse image says.
    """

    domain: str = eqx.field(static=True, default="likelihood")
    # An array (a leaf), not static: its default comes from the photo's noise, and photos
    # of one fit config then share one compiled solve.
    floor: Float[Array, ""] | None = eqx.field(converter=_optional_float, default=None)
    censoring: str = eqx.field(static=True, default="survival")
    factor: int = eqx.field(static=True, default=1)
    #: The scoring form of the likelihood's residuals (see :func:`pixel_residuals`).
    information: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        if self.domain not in PIXEL_DOMAINS:
            raise ConfigError(
                f"pixel view domain {self.domain!r} is not one of {', '.join(PIXEL_DOMAINS)}"
            )
        if self.censoring not in ("survival", "exclude"):
            raise ConfigError(
                f"pixel view censoring {self.censoring!r} is not one of survival, exclude"
            )
        if int(self.factor) != self.factor or self.factor < 1:
            raise ConfigError(f"downsampling factor must be an integer >= 1, got {self.factor!r}")
        if self.information and (self.domain != "likelihood" or self.factor != 1):
            raise ConfigError("the information form is that of the full-resolution likelihood")

    @property
    def likelihood(self) -> bool:
        """Whether this view's residuals are those of the photo's likelihood."""
        return self.domain == "likelihood"

    def __call__(self, ctx: ViewContext) -> Float[Array, " n"]:
        f = self.factor
        if f == 1:
            return pixel_residuals(
                ctx.target, ctx.expected, ctx.obs, domain=self.domain, floor=self.floor,
                saturated=ctx.saturated, censoring=self.censoring, information=self.information,
            )  # fmt: skip
        t = box_downsample(ctx.target, f)
        e = box_downsample(ctx.expected, f)
        blocked = box_downsample(ctx.saturated.astype(t.dtype), f) > 0
        floor = None if self.floor is None else self.floor * f * f
        return pixel_residuals(
            t, e, ctx.obs, domain=self.domain, floor=floor, saturated=blocked,
            censoring=self.censoring, read_noise_scale=f, censor_level=t,
        )  # fmt: skip

    def size(self, shape):
        return (shape[0] // self.factor) * (shape[1] // self.factor)


#: Options of the statistics views (radial, angular, halo) for the scatter between eyes
#: with the same parameters (:mod:`invglare.fit.draw_scatter`): `draws`, how many other
#: eyes to simulate (0: none); `offset` and `whiten`, what the simulation measured (set by
#: :func:`invglare.fit.draw_scatter.scatter_options`, not by hand); `model_draws`, over
#: how many eyes the model's prediction is averaged (1: its own draw only), which smooths
#: the statistic's dependence on the parameters.
SCATTER_FIELDS = ("draws", "model_draws", "offset", "whiten")


def _optional_array(x):
    return None if x is None else jnp.asarray(x)


def whitened(
    r: Float[Array, " n"], offset: Float[Array, " n"] | None, whiten: Float[Array, "n n"] | None
) -> Float[Array, " n"]:
    """``whiten @ (r - offset)``: a statistic's residual, its model side corrected to the mean
    of many eyes, in units of the scatter between eyes (`r` where nothing was measured)."""
    if offset is not None:
        r = r - offset.astype(r.dtype)
    if whiten is not None:
        r = whiten.astype(r.dtype) @ r
    return r


class _StatisticView(AbstractView):
    """A statistics view: its :meth:`raw` residual, whitened by the scatter between eyes (the
    :data:`SCATTER_FIELDS`, keyword-only, so that each view's own fields keep their places)."""

    draws: int = eqx.field(static=True, default=0, kw_only=True)
    model_draws: int = eqx.field(static=True, default=1, kw_only=True)
    offset: Float[Array, " n"] | None = eqx.field(
        converter=_optional_array, default=None, kw_only=True
    )
    whiten: Float[Array, "n n"] | None = eqx.field(
        converter=_optional_array, default=None, kw_only=True
    )

    def __call__(self, ctx):
        return whitened(self.raw(ctx), self.offset, self.whiten)

    @abc.abstractmethod
    def raw(self, ctx: ViewContext) -> Float[Array, " n"]:
        """The residual before the scatter's whitening."""


class RadialView(_StatisticView):
    """Log ratio of the target's and the model's radial profiles (clipped prediction).

    ``log(P_t + floor) - log(P_m + floor)`` per ring, `floor` in counts per pixel
    (below it the profile is noise). Rings of ``max_radius_px / n_bins`` px.
    With the scatter between eyes measured (see :data:`SCATTER_FIELDS`), the residual is
    whitened by it.
    """

    n_bins: int = eqx.field(static=True)
    max_radius_px: float = eqx.field(static=True)
    floor: Float[Array, ""] = eqx.field(converter=as_float)  # a leaf, as PixelView's

    def raw(self, ctx):
        pt = radial_profile(ctx.target, ctx.centre, self.n_bins, self.max_radius_px)
        pm = radial_profile(ctx.predicted, ctx.centre, self.n_bins, self.max_radius_px)
        return jnp.log(jnp.maximum(pt, 0.0) + self.floor) - jnp.log(
            jnp.maximum(pm, 0.0) + self.floor
        )

    def size(self, shape):
        return self.n_bins


class AngularView(_StatisticView):
    """Difference of the energy fractions per angular sector, times `n_bins` (so O(1)).

    Both images have the model's current background removed first; the
    fractions make the view independent of the flux, so it constrains
    directions (blade rotation, lash angles, streaks) only. Whitened by the scatter
    between eyes where it is measured (:data:`SCATTER_FIELDS`).
    """

    n_bins: int = eqx.field(static=True)
    r_min: float = eqx.field(static=True)
    r_max: float = eqx.field(static=True)

    def raw(self, ctx):
        bg = ctx.obs.response * ctx.obs.background
        et = angular_energy(ctx.target - bg, ctx.centre, self.n_bins, self.r_min, self.r_max)
        em = angular_energy(ctx.predicted - bg, ctx.centre, self.n_bins, self.r_min, self.r_max)
        ft = et / jnp.sum(et)
        fm = em / jnp.sum(em)
        return self.n_bins * (ft - fm)

    def size(self, shape):
        return self.n_bins


class HaloView(_StatisticView):
    """Target minus model halo ring radius (px), see :func:`halo_ring_radius`; whitened
    by the scatter between eyes where it is measured (:data:`SCATTER_FIELDS`)."""

    r_core: float = eqx.field(static=True)
    r_max: float = eqx.field(static=True)
    power: float = eqx.field(static=True, default=2.0)

    def raw(self, ctx):
        bg = ctx.obs.response * ctx.obs.background
        kw = dict(background=bg, power=self.power)
        rt = halo_ring_radius(ctx.target, ctx.centre, self.r_core, self.r_max, **kw)
        rm = halo_ring_radius(ctx.predicted, ctx.centre, self.r_core, self.r_max, **kw)
        return jnp.reshape(rt - rm, (1,))

    def size(self, shape):
        return 1


#: View names accepted by :func:`make_residual_fn`, with their classes.
VIEWS: dict[str, type[AbstractView]] = {
    "pixels": PixelView,
    "log": PixelView,
    "radial": RadialView,
    "angular": AngularView,
    "halo": HaloView,
}


def _noise_floor(obs: Observation) -> float:
    """Standard deviation (counts) of a background pixel: the level below which data is noise."""
    bg = max(float(obs.response * obs.background), 0.0)
    return math.sqrt(bg / float(obs.gain) + float(obs.read_noise) ** 2)


def _defaults(name: str, shape, obs: Observation, target: np.ndarray) -> dict:
    """Options of a view that depend on the image: sizes, radii and floors."""
    r_max = float(min(shape) // 2 - 1)
    floor = max(_noise_floor(obs), 1e-6 * float(np.max(np.abs(target))), 1e-30)
    if name == "pixels":
        return {}
    if name == "log":
        return {"domain": "log", "floor": 3.0 * floor}
    if name == "radial":
        return {"n_bins": int(r_max), "max_radius_px": r_max, "floor": floor}
    if name == "angular":
        return {"n_bins": 72, "r_min": 3.0, "r_max": r_max}
    return {"r_core": 4.0, "r_max": r_max}


def build_view(
    name: str, options: Mapping[str, Any] | None, shape, obs: Observation, target: np.ndarray
) -> AbstractView:
    """One view by name, with image-dependent defaults; unknown names or options: `ConfigError`."""
    if name not in VIEWS:
        raise ConfigError(f"unknown view {name!r}; valid views: {', '.join(VIEWS)}")
    cls = VIEWS[name]
    kwargs = _defaults(name, shape, obs, target)
    valid = [f.name for f in dataclasses.fields(cls)]
    for key in options or {}:
        if key not in valid:
            raise ConfigError(
                f"view {name!r} has no option {key!r}; valid options: {', '.join(valid)}"
            )
    kwargs.update(options or {})
    try:
        return cls(**kwargs)
    except TypeError as err:
        raise ConfigError(f"view {name!r}: {err}") from None


def _scored_apart(view: AbstractView) -> bool:
    """A pixel view of the likelihood at full resolution: the information comes from its
    scoring form, not from its deviance residuals (:meth:`ResidualFn.information_form`)."""
    return isinstance(view, PixelView) and view.likelihood and view.factor == 1


class ResidualFn(eqx.Module):
    """Residuals of a fit as an optimistix function ``fn(latent, args) -> vector``.

    `latent` is the unconstrained vector of `space`; the residual is the
    concatenation over views of ``sqrt(weight) * residuals``, then the residuals of the
    joint `priors` of the free parameters (a fitted eyelash layout's, see
    :mod:`invglare.fit.lash_prior`). `args` is unused (the data live in the module, so
    `jit` sees them as arguments, not constants).
    """

    space: ParameterSpace = eqx.field(static=True)
    forward: Forward
    target: Float[Array, "h w"]
    saturated: Bool[Array, "h w"]
    views: tuple
    names: tuple[str, ...] = eqx.field(static=True)
    weights: tuple[float, ...] = eqx.field(static=True)
    priors: tuple = ()
    #: Latent steps (one per parameter) of central differences, the trend of statistics of
    #: unresolved draws (:mod:`invglare.fit.trend_jacobian`); empty: exact derivatives.
    trend_step: tuple[float, ...] = eqx.field(static=True, default=())
    #: > 1: the prediction is averaged over this many eyes (`mean_prediction` of
    #: :mod:`invglare.fit.redraw`); 1: the model's own draw.
    model_draws: int = eqx.field(static=True, default=1)

    def forward_at(self, latent: Float[Array, " p"] | Sequence[Array]) -> Forward:
        """The forward model with the free parameters set from `latent` (a vector, or a
        list of scalars: see :meth:`at_parts`)."""
        if isinstance(latent, list | tuple):
            values = self.space.from_latent_parts(latent)
        else:
            values = self.space.from_latent(latent)
        return self.space.apply(self.forward, values)

    def context(self, latent: Float[Array, " p"] | Sequence[Array]) -> ViewContext:
        fwd = self.forward_at(latent)
        expected, predicted = mean_prediction(fwd, self.model_draws)
        h, w = self.target.shape
        centre = (w // 2 + fwd.obs.dx_px, h // 2 + fwd.obs.dy_px)
        return ViewContext(self.target, self.saturated, expected, predicted, fwd.obs, centre)

    def per_view(self, latent: Float[Array, " p"]) -> dict[str, Float[Array, " n"]]:
        """Unweighted residuals of each view."""
        ctx = self.context(latent)
        return {n: v(ctx) for n, v in zip(self.names, self.views, strict=True)}

    def __call__(self, latent: Float[Array, " p"], args: Any = None) -> Float[Array, " n"]:
        del args
        return self.at_parts([latent[i] for i in range(self.space.size)])

    def at_parts(self, parts: Sequence[Array]) -> Float[Array, " n"]:
        """The residuals at the latent values `parts`, a list of scalars.

        Kept apart, a forward derivative in one of them only runs through the part of the
        model that parameter touches (a flux column is one multiply, not a tangent FFT):
        :func:`invglare.fit.solve.jacobian_columns` builds the Jacobian this way.
        """
        if self.trend_step:
            return trend_residuals(self, parts)
        return self.exact_at_parts(parts)

    def exact_at_parts(self, parts: Sequence[Array]) -> Float[Array, " n"]:
        """:meth:`at_parts` differentiated exactly, whatever `trend_step` says."""
        return self._weighted(self.context(list(parts)), list(parts))

    def evaluate(self, latent: Float[Array, " p"]) -> tuple[Float[Array, " n"], ViewContext]:
        """The residuals and the context they came from (one model evaluation)."""
        ctx = self.context(latent)
        return self._weighted(ctx, latent), ctx

    def _weighted(
        self, ctx: ViewContext, latent: Float[Array, " p"] | Sequence[Array]
    ) -> Float[Array, " n"]:
        weighted = [
            math.sqrt(wt) * v(ctx).astype(self.target.dtype)
            for v, wt in zip(self.views, self.weights, strict=True)
        ]
        if self.priors:
            fwd = self.forward_at(latent)
            weighted.append(prior_residuals(self.priors, fwd).astype(self.target.dtype))
        return jnp.concatenate(weighted)

    def loss(self, latent: Float[Array, " p"]) -> Float[Array, ""]:
        """``sum(residuals**2)`` (chi-square when every view is noise-normalised)."""
        r = self(latent)
        return jnp.sum(r * r)

    def with_factor(self, factor: int) -> ResidualFn:
        """The same residuals with the pixel views on `factor`-times coarser blocks."""
        views = tuple(
            dataclasses.replace(v, factor=factor) if isinstance(v, PixelView) else v
            for v in self.views
        )
        return dataclasses.replace(self, views=views)

    # ---- the likelihood

    @property
    def pure_likelihood(self) -> bool:
        """Whether ``sum(r**2) / 2`` is ``-log L`` plus a constant: one full-resolution pixel
        view in the likelihood domain, weight 1 (with a lash layout's prior residuals, the
        log posterior's, as the sampler's)."""
        return (
            len(self.views) == 1
            and isinstance(self.views[0], PixelView)
            and self.views[0].likelihood
            and self.views[0].factor == 1
            and self.weights[0] == 1.0
        )

    @property
    def draw_whitened(self) -> bool:
        """Whether a statistics view is whitened by the scatter between eyes (`draws`): the
        photo is then taken as another eye than the model's draw, so the pixel likelihood of
        that draw is not this fit's likelihood."""
        return any(getattr(v, "whiten", None) is not None for v in self.views)

    def stabilised_views(self) -> tuple[str, ...]:
        """Names of the pixel views in a variance-stabilised domain (starts only)."""
        return tuple(
            n
            for n, v in zip(self.names, self.views, strict=True)
            if isinstance(v, PixelView) and v.domain in STABILISED_DOMAINS
        )

    def with_likelihood(self) -> ResidualFn:
        """The same views with every variance-stabilised pixel view in the likelihood domain."""
        views = tuple(
            dataclasses.replace(v, domain="likelihood")
            if isinstance(v, PixelView) and v.domain in STABILISED_DOMAINS
            else v
            for v in self.views
        )
        check_likelihood_photo(self.forward.obs, self.target, self.saturated)
        return dataclasses.replace(self, views=views)

    def likelihood_only(self) -> ResidualFn:
        """The photo's likelihood alone: one full-resolution pixel view, weight 1 (keeping a
        pixel view's censoring)."""
        censoring = next((v.censoring for v in self.views if isinstance(v, PixelView)), "survival")
        check_likelihood_photo(self.forward.obs, self.target, self.saturated)
        view = PixelView(domain="likelihood", censoring=censoring)
        # Pixels are differentiated exactly, against the model's own draw.
        return dataclasses.replace(
            self, views=(view,), names=("pixels",), weights=(1.0,), trend_step=(), model_draws=1
        )

    def unwhitened(self) -> ResidualFn:
        """These residuals with no statistics view weighed by a measured scatter (`offset`
        and `whiten` None): what a view's :meth:`~_StatisticView.raw` residual needs, as one
        program structure whether or not a scatter has been measured yet."""
        views = tuple(
            dataclasses.replace(v, offset=None, whiten=None) if isinstance(v, _StatisticView) else v
            for v in self.views
        )
        return dataclasses.replace(self, views=views)

    def information_form(self) -> ResidualFn:
        """The likelihood's pixel views in their scoring form (see :func:`pixel_residuals`):
        ``J^T J`` is then the Fisher information plus the other views' Gauss–Newton terms."""
        views = tuple(
            dataclasses.replace(v, information=True) if _scored_apart(v) else v for v in self.views
        )
        return dataclasses.replace(self, views=views)

    @property
    def scores_itself(self) -> bool:
        """Whether :meth:`information_form` is these residuals unchanged (no view of the
        pixel likelihood at full resolution): their own Jacobian gives the information."""
        return not any(_scored_apart(v) for v in self.views)

    def objective(self) -> str:
        """What the residuals' sum of squares is, in words (for a report)."""
        parts = []
        for name, view, weight in zip(self.names, self.views, self.weights, strict=True):
            if isinstance(view, PixelView) and view.likelihood:
                what = "the Poisson–Gaussian likelihood of the pixels (deviance residuals"
                what += ", clipped pixels censored)" if view.censoring == "survival" else ")"
            elif isinstance(view, PixelView):
                what = f"pixels in the {view.domain} domain"
            else:
                what = f"the {name} view"
            parts.append(what + (f" × {weight:g}" if weight != 1.0 else ""))
        return " + ".join(parts)


def check_likelihood_photo(
    obs: Observation, target: Float[ArrayLike, "h w"], saturated: Bool[ArrayLike, "h w"]
) -> None:
    """Refuse a photo whose likelihood is degenerate: pixels at or below 0 counts with no
    read noise have no variance in the Poisson–Gaussian model (`ConfigError`)."""
    read = obs.read_noise
    if isinstance(read, jax.core.Tracer) or float(read) > 0:
        return
    dark = (np.asarray(target) <= 0) & ~np.asarray(saturated, bool)
    if dark.any():
        raise ConfigError(
            f"the photo has {int(dark.sum())} pixels at or below 0 counts and the noise model "
            "no read noise: the Poisson–Gaussian likelihood gives them no variance; set "
            "observation.read_noise to the camera's read noise (counts rms, > 0)"
        )


def make_residual_fn(
    space: ParameterSpace,
    forward_template: Forward,
    target: Float[ArrayLike, "h w"],
    views: Mapping[str, float],
    *,
    view_options: Mapping[str, Mapping[str, Any]] | None = None,
    factor: int = 1,
) -> ResidualFn:
    """Build the residual function of a fit (validating paths, views and the target).

    **Arguments:**

    - `space`: the free parameters (paths into `forward_template`).
    - `forward_template`: a :class:`~invglare.fit.Forward` holding the fixed values.
    - `target`: the photo, counts, same shape as the model's output.
    - `views`: ``{name: weight}`` with names from :data:`VIEWS`; weights >= 0.
    - `view_options`: ``{name: {option: value}}``, e.g.
      ``{"angular": {"n_bins": 36, "r_min": 5.0}}``; unset options get defaults
      from the image size and the noise level.
    - `factor`: block size of the pixel views (coarse-to-fine stages).

    **Returns:** a :class:`ResidualFn`, ``fn(latent, args) -> residuals``.

    **Example:**

    ```python
    fn = make_residual_fn(space, Forward(model, obs), photo, {"pixels": 1.0, "radial": 0.1})
    r = fn(space.initial_latent(), None)
    ```
    """
    if not isinstance(forward_template, Forward):
        raise ConfigError(
            f"forward_template must be a Forward(model, obs), got {type(forward_template).__name__}"
        )
    space.check(forward_template)
    forward_template = specialise_forward(space, forward_template)
    if not isinstance(views, Mapping) or not views:
        raise ConfigError(f"views must be a non-empty mapping name -> weight, got {views!r}")
    options = dict(view_options or {})
    for name in options:
        if name not in views:
            raise ConfigError(f"view_options names view {name!r}, which is not among the views")
    out_shape = eqx.filter_eval_shape(forward_template).shape
    obs = forward_template.obs
    tgt = check_target(target, shape=out_shape, saturation=obs.saturation)
    built, names, weights = [], [], []
    for name, weight in views.items():
        if name not in VIEWS:
            raise ConfigError(f"unknown view {name!r}; valid views: {', '.join(VIEWS)}")
        wt = float(weight)
        if not (math.isfinite(wt) and wt >= 0):
            raise ConfigError(f"view {name!r} weight must be finite and >= 0, got {weight!r}")
        view = build_view(name, options.get(name), out_shape, obs, tgt)
        if isinstance(view, PixelView):
            view = dataclasses.replace(view, factor=factor)
        built.append(view)
        names.append(name)
        weights.append(wt)
    dtype = jnp.result_type(float)
    target_arr = jnp.asarray(tgt, dtype=dtype)
    if any(isinstance(v, PixelView) and v.likelihood for v in built):
        check_likelihood_photo(obs, tgt, obs.saturated_mask(tgt))
    return ResidualFn(
        # Without the photo's starting guesses: one compiled solve serves every photo.
        space=space.structure(),
        forward=forward_template,
        target=target_arr,
        saturated=obs.saturated_mask(target_arr),
        views=tuple(built),
        names=tuple(names),
        weights=tuple(weights),
        priors=layout_priors(space, forward_template),
        trend_step=trend_steps(space) if any(getattr(v, "draws", 0) for v in built) else (),
        model_draws=max(getattr(v, "model_draws", 1) for v in built),
    )
