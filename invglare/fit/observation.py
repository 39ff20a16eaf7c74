"""The observation model: from a unit-energy PSF to the photo a camera would record.

A target photo is linear (not tone-mapped) counts per pixel. The model of it is

```
psf  --scale_psf(pixel_scale_ratio)-->  --rotate(rotation_deg)-->
     --convolve(source disk)-->  --shift(dx_px, dy_px)-->  s        (unit energy)
expected  = response * (flux * s + background)                      (counts, unclipped)
predicted = softmin(expected, saturation)                           (what the photo shows)
```

with a Poisson–Gaussian noise model ``variance = expected / gain + read_noise**2``
(counts²; `gain` is in electrons per count, `read_noise` in counts rms).

:class:`Forward` ties a model and an :class:`Observation` into one pytree whose
leaves are all addressable by path (``"model.aperture.shapes[0].diameter_mm"``,
``"obs.flux"``), so nuisance parameters are fitted exactly like model parameters.

Coordinates: x along columns, y along rows, both measured from pixel
``(H // 2, W // 2)``; angles counter-clockwise from +x towards +y, as for the
apertures. Because rows grow downwards when an array is displayed, a rotation by
+90° here is ``np.rot90(image, k=-1)`` (numpy's default turns the other way).
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Collection

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.ndimage import map_coordinates
from jax.scipy.special import log_ndtr
from jaxtyping import Array, ArrayLike, Bool, Float, Int, PRNGKeyArray

from invglare._core.checks import as_float
from invglare.errors import ConfigError, InputDataError, PhysicsRangeError
from invglare.optics.spectral import scale_psf

CENSORING = ("survival", "exclude")

#: An observed pixel at or above ``saturation * (1 - SATURATED_RTOL)`` counts as clipped.
SATURATED_RTOL = 1e-4


def _concrete(x) -> np.ndarray | None:
    return None if isinstance(x, jax.core.Tracer) else np.asarray(x, dtype=float)


def _check(name: str, value, *, positive: bool = False, nonneg: bool = False) -> None:
    arr = _concrete(value)
    if arr is None:
        return
    bad = ~np.isfinite(arr)
    if positive:
        bad |= arr <= 0
    if nonneg:
        bad |= arr < 0
    if np.any(bad):
        want = "finite and > 0" if positive else "finite and >= 0" if nonneg else "finite"
        raise PhysicsRangeError(f"observation {name} must be {want}, got {arr.ravel()[0]:g}")


# --------------------------------------------------------------------------------------
# image operations (pure functions, differentiable in their real arguments)


def rotate_image(image: Float[ArrayLike, "h w"], angle_deg: ArrayLike) -> Float[Array, "h w"]:
    """Rotate `image` by `angle_deg` (counter-clockwise, +x towards +y) about pixel (h//2, w//2).

    Bilinear resampling, zero outside the frame; differentiable in the angle
    (piecewise, with kinks where a sample crosses a pixel centre). Energy is kept
    up to interpolation smoothing and what leaves the frame.

    **Example:** for odd sizes ``rotate_image(a, 90.0)`` equals ``np.rot90(a, k=-1)``.
    """
    image = jnp.asarray(image)
    h, w = image.shape
    th = jnp.deg2rad(jnp.asarray(angle_deg, dtype=image.dtype))
    c, s = jnp.cos(th), jnp.sin(th)
    y = jnp.arange(h, dtype=image.dtype)[:, None] - h // 2
    x = jnp.arange(w, dtype=image.dtype)[None, :] - w // 2
    # Each output pixel reads the input at the inversely rotated position.
    x_in = c * x + s * y
    y_in = -s * x + c * y
    return map_coordinates(image, [y_in + h // 2, x_in + w // 2], order=1, mode="constant")


def disk_kernel(shape: tuple[int, int], radius_px: ArrayLike, dtype=None) -> Float[Array, "h w"]:
    """A unit-sum disk of `radius_px` centred on pixel (h//2, w//2), anti-aliased.

    Each pixel's weight is ``clip(radius + 1/2 - r, 0, 1)`` (a linear edge one
    pixel wide), so the kernel is continuous in the radius; below half a pixel it
    is a single pixel (a point source).
    """
    h, w = shape
    dtype = dtype or jnp.result_type(float)
    y = jnp.arange(h, dtype=dtype)[:, None] - h // 2
    x = jnp.arange(w, dtype=dtype)[None, :] - w // 2
    r = jnp.sqrt(x * x + y * y)
    k = jnp.clip(jnp.asarray(radius_px, dtype=dtype) + 0.5 - r, 0.0, 1.0)
    return k / jnp.sum(k)


def fourier_shift(
    image: Float[ArrayLike, "h w"],
    dx_px: ArrayLike,
    dy_px: ArrayLike,
    kernel: Float[ArrayLike, "h w"] | None = None,
) -> Float[Array, "h w"]:
    """Shift `image` by (dx, dy) px with a Fourier phase ramp; optionally convolve with `kernel`.

    Exact for band-limited images and smooth in the shift; the frame wraps
    around (periodic), which is harmless for a PSF that has decayed at its border.
    `kernel` (centred on pixel (h//2, w//2), e.g. :func:`disk_kernel`) is applied
    in the same FFT.
    """
    image = jnp.asarray(image)
    h, w = image.shape
    # Real image, real result: half spectra (rfft2), about half the work of fft2 + ifft2.
    # The phase ramp is separable; at an even size's Nyquist frequency (its own mirror)
    # the ramp's Hermitian part cos(pi d) replaces exp(i pi d) (at the corner of two even
    # sizes, cos(pi (dx + dy))), which is what taking the real part of the full inverse
    # transform did: the result is the same.
    phase = (
        _shift_ramp(h, dy_px, image.dtype)[:, None]
        * _shift_ramp(w, dx_px, image.dtype)[None, : w // 2 + 1]
    )
    if h % 2 == 0 and w % 2 == 0:  # the corner is its own mirror in both axes at once
        corner = jnp.cos(math.pi * (jnp.asarray(dx_px) + jnp.asarray(dy_px))).astype(image.dtype)
        phase = phase.at[h // 2, w // 2].set(corner)
    spectrum = jnp.fft.rfft2(image) * phase
    if kernel is not None:
        spectrum = spectrum * jnp.fft.rfft2(jnp.fft.ifftshift(jnp.asarray(kernel)))
    return jnp.fft.irfft2(spectrum, s=(h, w)).astype(image.dtype)


def _shift_ramp(n: int, shift: ArrayLike, dtype) -> Array:
    """``exp(-2 pi i k shift)`` over ``fftfreq(n)``, ``cos(pi shift)`` at an even `n`'s Nyquist."""
    k = jnp.fft.fftfreq(n).astype(dtype)
    ramp = jnp.exp(-2j * math.pi * k * shift)
    if n % 2 == 0:
        ramp = ramp.at[n // 2].set(jnp.cos(math.pi * jnp.asarray(shift, dtype)))
    return ramp


def soft_clip(
    x: Float[ArrayLike, "*shape"], level: float, softness: float = 0.01
) -> Float[Array, "*shape"]:
    """Smooth ``min(x, level)``: ``level - w softplus((level - x) / w)``, ``w = softness * level``.

    Below the level by a few `w` it is `x` (to ``w * exp(-(level - x) / w)``); far
    above it is `level`; the slope ``sigmoid((level - x) / w)`` falls from 1 to 0
    over a few `w` instead of jumping, so a fit whose prediction crosses the clip
    level keeps a gradient. At ``x = level`` the value is ``level - w log 2``.
    """
    x = jnp.asarray(x)
    width = softness * level
    return level - width * jax.nn.softplus((level - x) / width)


# --------------------------------------------------------------------------------------
# the observation


class Observation(eqx.Module):
    """How a unit-energy PSF becomes counts in a photo: geometry, photometry, noise, clipping.

    **Fields** (array leaves; fit any of them as ``"obs.<name>"``):

    - `flux`: total source counts (the sum of the unclipped source image), counts.
    - `background`: uniform background, counts per pixel.
    - `dx_px`, `dy_px`: source centre minus pixel (W//2, H//2), photo pixels (x = column).
    - `rotation_deg`: rotation of the PSF about its centre, counter-clockwise from +x to +y.
    - `pixel_scale_ratio`: model pixel scale / photo pixel scale; the PSF is
      magnified by it (:func:`invglare.optics.spectral.scale_psf`).
    - `response`: the camera's linear response, multiplying source and background
      (a known exposure or ISO ratio; degenerate with flux and background, so
      normally fixed at 1).
    - `gain`: electrons per count (Poisson part of the noise).
    - `read_noise`: read noise, counts rms.
    - `source_radius_px`: optional angular radius of the source, photo pixels
      (``None``: a point source); the PSF is convolved with a disk of that radius.

    **Static configuration:**

    - `saturation`: clip level in counts (``None``: no clipping).
    - `clip_softness`: width of the smooth clip as a fraction of `saturation`
      (see :func:`soft_clip`).

    **Example:**

    ```python
    obs = Observation(flux=1e6, background=20.0, dx_px=0.3, read_noise=3.0, saturation=6e4)
    photo = obs(psf)                    # predicted photo, soft-clipped
    var = obs.variance(obs.expected(psf))
    ```
    """

    flux: Float[Array, ""] = eqx.field(converter=as_float, default=1.0)
    background: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)
    dx_px: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)
    dy_px: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)
    rotation_deg: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)
    pixel_scale_ratio: Float[Array, ""] = eqx.field(converter=as_float, default=1.0)
    response: Float[Array, ""] = eqx.field(converter=as_float, default=1.0)
    gain: Float[Array, ""] = eqx.field(converter=as_float, default=1.0)
    read_noise: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)
    source_radius_px: Float[Array, ""] | None = eqx.field(
        converter=lambda x: None if x is None else as_float(x), default=None
    )
    saturation: float | None = eqx.field(static=True, default=None)
    clip_softness: float = eqx.field(static=True, default=0.01)
    #: Geometry steps skipped as the identity ("scale", "rotation"): set by
    #: :meth:`with_fixed_geometry` for a fit in which they stay exactly neutral.
    identity_steps: tuple[str, ...] = eqx.field(static=True, default=())

    def __check_init__(self):
        for name in ("flux", "background", "dx_px", "dy_px", "rotation_deg"):
            _check(name, getattr(self, name))
        _check("pixel_scale_ratio", self.pixel_scale_ratio, positive=True)
        _check("response", self.response, positive=True)
        _check("gain (electrons per count)", self.gain, positive=True)
        _check("read_noise (counts)", self.read_noise, nonneg=True)
        if self.source_radius_px is not None:
            _check("source_radius_px", self.source_radius_px, nonneg=True)
        if self.saturation is not None and not (
            math.isfinite(self.saturation) and self.saturation > 0
        ):
            raise PhysicsRangeError(
                f"observation saturation must be a finite level > 0 counts or None, "
                f"got {self.saturation!r}"
            )
        if not (0 < self.clip_softness < 1):
            raise PhysicsRangeError(
                f"observation clip_softness must lie in (0, 1), got {self.clip_softness!r}"
            )

    @classmethod
    def from_target(
        cls, target: Float[ArrayLike, "h w"], *, border_px: int = 4, **fields
    ) -> Observation:
        """An observation whose flux and background are guessed from a photo.

        Background: the median of a `border_px`-wide frame (the source should be
        well inside it). Flux: the sum of the photo minus that background (a lower
        bound when the core is clipped). Any field can be given in `fields`.
        """
        t = np.asarray(target, dtype=float)
        frame = np.concatenate(
            [t[:border_px].ravel(), t[-border_px:].ravel(), t[:, :border_px].ravel(),
             t[:, -border_px:].ravel()]
        )  # fmt: skip
        bg = float(np.median(frame))
        flux = max(float(np.sum(t - bg)), 1e-12 * max(float(np.max(np.abs(t))), 1.0))
        fields.setdefault("background", bg)
        fields.setdefault("flux", flux)
        return cls(**fields)

    # ---- prediction

    def transform_psf(self, psf: Float[Array, "h w"]) -> Float[Array, "h w"]:
        """The PSF on the photo's pixel grid: scaled, rotated, blurred by the source, shifted.

        Negative values are set to 0. A PSF still bright where the field ends (a
        cross-screen filter's streaks run off the frame) rings under the sub-pixel
        Fourier shift, and a negative mean count is no model of a photo: its pixels
        read ~0, which no parameter could then explain.
        """
        psf = jnp.asarray(psf)
        dtype = psf.dtype
        out = psf
        if "scale" not in self.identity_steps:
            out = scale_psf(out, self.pixel_scale_ratio.astype(dtype))
        if "rotation" not in self.identity_steps:
            out = rotate_image(out, self.rotation_deg.astype(dtype))
        kernel = None
        if self.source_radius_px is not None:
            kernel = disk_kernel(psf.shape, self.source_radius_px, dtype)
        out = fourier_shift(out, self.dx_px.astype(dtype), self.dy_px.astype(dtype), kernel)
        return jnp.maximum(out, 0.0)

    def with_fixed_geometry(self, free: Collection[str] = ()) -> Observation:
        """A copy that skips the rescaling and the rotation where they are the identity.

        A step is skipped when its value is exactly neutral (``pixel_scale_ratio`` 1,
        ``rotation_deg`` 0) and its field is not among the `free` field names (those a
        fit or a sampler will change). Resampling at the identity
        returns the image unchanged, so the prediction is the same, for about a
        millisecond less per 256² evaluation. Traced values are left as they are.
        """
        steps = []
        for step, name, neutral in (
            ("scale", "pixel_scale_ratio", 1.0),
            ("rotation", "rotation_deg", 0.0),
        ):
            value = getattr(self, name)
            if name in free or isinstance(value, jax.core.Tracer):
                continue
            if float(value) == neutral:
                steps.append(step)
        return dataclasses.replace(self, identity_steps=tuple(steps))

    def expected(self, psf: Float[Array, "h w"]) -> Float[Array, "h w"]:
        """Mean counts per pixel before clipping: ``response * (flux * psf' + background)``."""
        s = self.transform_psf(psf)
        return self.response.astype(s.dtype) * (
            self.flux.astype(s.dtype) * s + self.background.astype(s.dtype)
        )

    def clip(self, expected: Float[Array, "h w"]) -> Float[Array, "h w"]:
        """The camera's clip at `saturation` (smooth, :func:`soft_clip`); identity without one."""
        if self.saturation is None:
            return expected
        return soft_clip(expected, self.saturation, self.clip_softness)

    def __call__(self, psf: Float[Array, "h w"]) -> Float[Array, "h w"]:
        """The predicted photo (mean counts, clipped)."""
        return self.clip(self.expected(psf))

    # ---- noise

    def variance(self, expected: Float[ArrayLike, "*shape"]) -> Float[Array, "*shape"]:
        """Poisson–Gaussian variance in counts²: ``max(expected, 0) / gain + read_noise**2``.

        `expected` is the unclipped mean in counts; with `gain` in electrons per
        count, ``expected * gain`` electrons have variance ``expected * gain``,
        i.e. ``expected / gain`` counts².
        """
        e = jnp.asarray(expected)
        return (
            jnp.maximum(e, 0.0) / self.gain.astype(e.dtype) + self.read_noise.astype(e.dtype) ** 2
        )

    def saturated_mask(self, observed: Float[ArrayLike, "*shape"]) -> Bool[Array, "*shape"]:
        """Pixels of a photo at the clip level (all False without a saturation level)."""
        o = jnp.asarray(observed)
        if self.saturation is None:
            return jnp.zeros(o.shape, dtype=bool)
        return o >= self.saturation * (1.0 - SATURATED_RTOL)

    def log_likelihood(
        self,
        observed: Float[ArrayLike, "h w"],
        expected: Float[ArrayLike, "h w"],
        *,
        censoring: str = "survival",
        mask: Bool[ArrayLike, "h w"] | None = None,
        censored: Int[ArrayLike, " k"] | None = None,
    ) -> Float[Array, ""]:
        """Log-likelihood of a photo given the *unclipped* mean `expected` (Gaussian approximation).

        Unsaturated pixels: ``-((o - e)**2 / V + log(2 pi V)) / 2`` with ``V =
        variance(e)``. Saturated pixels are censored: all we know is that the
        pixel would have read at least the clip level, so

        - ``censoring="survival"`` (default) adds ``log P(o >= S) =
          log Phi((e - S) / sqrt(V))``: a model too faint there is penalised,
          one at or above the level is not;
        - ``censoring="exclude"`` drops them.

        `mask` (True = use) removes further pixels, e.g. hot pixels.

        `censored`, optional: the flat indices of the saturated pixels in use, when the photo
        is fixed (as while sampling; :meth:`censored_indices` gives them). The survival
        term is then evaluated at those pixels only: ``log Phi`` costs dozens of
        operations per pixel, and a photo has few saturated pixels.
        """
        if censoring not in CENSORING:
            raise ConfigError(f"censoring {censoring!r} is not one of {', '.join(CENSORING)}")
        o = jnp.asarray(observed)
        e = jnp.asarray(expected)
        var = self.variance(e)
        sat = self.saturated_mask(o)
        use = jnp.ones(o.shape, bool) if mask is None else jnp.asarray(mask, bool)
        gauss = -0.5 * ((o - e) ** 2 / var + jnp.log(2 * math.pi * var))
        total = jnp.sum(jnp.where(use & ~sat, gauss, 0.0))
        if censoring == "survival" and self.saturation is not None:
            if censored is None:
                surv = log_ndtr((e - self.saturation) / jnp.sqrt(var))
                total = total + jnp.sum(jnp.where(use & sat, surv, 0.0))
            else:
                at = jnp.asarray(censored)
                e_at, var_at = e.reshape(-1)[at], var.reshape(-1)[at]
                total = total + jnp.sum(log_ndtr((e_at - self.saturation) / jnp.sqrt(var_at)))
        return total

    def censored_indices(
        self, observed: Float[ArrayLike, "h w"], mask: Bool[ArrayLike, "h w"] | None = None
    ) -> Int[np.ndarray, " k"]:
        """Flat indices of a fixed photo's saturated pixels in use, for `log_likelihood`."""
        sat = np.asarray(self.saturated_mask(observed))
        if mask is not None:
            sat = sat & np.asarray(mask, bool)
        return np.flatnonzero(sat)

    def sample(self, key: PRNGKeyArray, psf: Float[Array, "h w"]) -> Float[Array, "h w"]:
        """A noisy photo: Poisson electrons, Gaussian read noise, then a hard clip.

        For synthetic targets and tests; counts, same dtype as `psf`.
        """
        e = self.expected(psf)
        k1, k2 = jax.random.split(key)
        electrons = jax.random.poisson(k1, jnp.maximum(e, 0.0) * self.gain, e.shape)
        photo = electrons.astype(e.dtype) / self.gain.astype(e.dtype)
        photo = photo + self.read_noise.astype(e.dtype) * jax.random.normal(k2, e.shape, e.dtype)
        if self.saturation is not None:
            photo = jnp.minimum(photo, self.saturation)
        return photo


# --------------------------------------------------------------------------------------
# model + observation


class Forward(eqx.Module):
    """A model and its observation as one pytree: ``Forward(model, obs)()`` is a predicted photo.

    Every float leaf is a path from here: ``"model.<path in the model>"`` and
    ``"obs.<field>"`` (see :func:`invglare.fit.valid_paths`). `model` is any
    equinox Module whose ``__call__()`` returns a 2-D PSF (unit energy, centred on
    pixel (H//2, W//2)) on the photo's grid.

    **Example:**

    ```python
    fwd = Forward(AperturePSF.build(...), Observation(flux=1e6, background=10.0))
    photo = fwd()
    fwd = eqx.tree_at(lambda f: f.obs.dx_px, fwd, 0.4)
    ```
    """

    model: eqx.Module
    obs: Observation

    def __check_init__(self):
        if not isinstance(self.obs, Observation):
            raise ConfigError(f"Forward.obs must be an Observation, got {type(self.obs).__name__}")
        if not callable(self.model):
            raise ConfigError(f"Forward.model must be callable, got {type(self.model).__name__}")

    def psf(self) -> Float[Array, "h w"]:
        """The model's PSF (checked to be a 2-D monochrome image)."""
        psf = jnp.asarray(self.model())
        if psf.ndim != 2:
            raise ConfigError(
                f"the model returns an array of shape {psf.shape}; fitting needs a monochrome "
                "PSF (h, w): use one wavelength, or wrap the model to return one channel"
            )
        return psf

    def expected(self) -> Float[Array, "h w"]:
        """Mean counts per pixel before clipping (what the noise model and censoring use)."""
        return self.obs.expected(self.psf())

    def predict(self) -> tuple[Float[Array, "h w"], Float[Array, "h w"]]:
        """``(expected, predicted)``: the unclipped mean and the clipped photo, one model call."""
        e = self.expected()
        return e, self.obs.clip(e)

    def __call__(self) -> Float[Array, "h w"]:
        return self.obs.clip(self.expected())


def check_target(
    target: ArrayLike, *, shape: tuple[int, int] | None = None, saturation: float | None = None
) -> np.ndarray:
    """Validate a target photo; return it as a float array.

    Raises :class:`~invglare.errors.InputDataError` naming the reason for: a
    non-2-D array or one whose shape differs from the model's `shape`; an 8-bit
    image (tone-mapped and quantised, not linear counts); NaN or infinite pixels;
    an image with no signal (all zeros, or constant); an image whose every pixel
    is at the `saturation` level.
    """
    arr = np.asarray(target)
    if arr.dtype == np.uint8:
        raise InputDataError(
            "the target is an 8-bit image; fitting needs a linear photo in counts (raw or "
            "linear HDR such as OpenEXR), not a tone-mapped 8-bit one"
        )
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise InputDataError(f"the target must hold numbers, got dtype {arr.dtype}")
    arr = arr.astype(np.float64 if arr.dtype == np.float64 else np.float32)
    if arr.ndim != 2:
        raise InputDataError(
            f"the target must be a 2-D monochrome image (h, w), got shape {arr.shape}"
        )
    if shape is not None and tuple(arr.shape) != tuple(shape):
        raise InputDataError(
            f"the target has shape {arr.shape} but the model predicts {tuple(shape)}; build "
            "the model on the photo's pixel grid"
        )
    bad = ~np.isfinite(arr)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise InputDataError(
            f"the target has {int(bad.sum())} non-finite (NaN or inf) pixels, the first at "
            f"row {r}, column {c}; mask or repair them before fitting"
        )
    if not np.any(arr):
        raise InputDataError("the target is all zeros: there is no signal to fit")
    if arr.min() >= 0 and arr.max() <= 1 and np.allclose(arr * 255, np.round(arr * 255), atol=1e-4):
        warnings.warn(
            "the target's values are all multiples of 1/255 in [0, 1]: it looks like a "
            "tone-mapped 8-bit image; fits need linear counts (raw or linear HDR)",
            stacklevel=2,
        )
    if saturation is not None and np.all(arr >= saturation * (1.0 - SATURATED_RTOL)):
        raise InputDataError(
            f"every pixel of the target is at the saturation level {saturation:g}: the photo "
            "is overexposed and holds no usable signal"
        )
    if np.ptp(arr) == 0:
        raise InputDataError(f"the target is constant ({arr.flat[0]:g}): there is no signal to fit")
    return arr
