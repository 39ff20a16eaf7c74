"""Tone mapping: from linear HDR values (cd/m^2) to display values.

Operators:

| name         | function             | paper                                  |
|--------------|----------------------|----------------------------------------|
| `"kakimoto"` | `kakimoto_tonemap`   | Kakimoto et al., sigmoid of eq. 6-7    |
| `"reinhard"` | `reinhard_display`   | Reinhard et al. 2002, global operator  |
| `"gamma"`    | `exposure_gamma`     | exposure, clip, power 1 / gamma        |
| `"srgb"`     | `srgb_display`       | exposure, clip, sRGB transfer function |

Every entry of `TONEMAPS` takes a linear image `(H, W)` or `(H, W, C)` and
keyword parameters, and returns display values in [0, 1] of the same shape,
ready for `invglare.files.write_png`; `tonemap(image, name, **params)` dispatches on
the name. The building blocks (`kakimoto_sigmoid` in the paper's 0-255 display
units, `reinhard_global` in linear display luminance, `srgb_encode`) are public
too. Everything is `jnp`, differentiable in the image and in every parameter, and
works under `jit` and `vmap` (parameters may be traced; they are range-checked
only when concrete).
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import NamedTuple

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from invglare._core.checks import as_float
from invglare._core.grids import check_positive
from invglare.errors import ConfigError, InputDataError, PhysicsRangeError
from invglare.render.bright import luminance

__all__ = [
    "DISPLAY_MAX",
    "TONEMAPS",
    "GlareLayers",
    "display_to_unit",
    "exposure_gamma",
    "kakimoto_glare_image",
    "kakimoto_glare_layers",
    "kakimoto_scene_scale",
    "kakimoto_sigmoid",
    "kakimoto_sigmoid_inverse",
    "kakimoto_tonemap",
    "log_average_luminance",
    "reinhard_display",
    "reinhard_global",
    "srgb_display",
    "srgb_encode",
    "tonemap",
]

#: Largest frame-buffer value of the paper's 8-bit display (its [0, 255] range).
DISPLAY_MAX = 255.0


def _safe_pow(x: Array, p) -> Array:
    """``x ** p`` for ``x >= 0`` and ``0 < p < 1``, with a zero (not NaN) gradient at x = 0."""
    positive = x > 0
    # As exp(p log x): XLA's CPU power of a float32 frame took 2.3 times as long (512² RGB).
    return jnp.where(positive, jnp.exp(p * jnp.log(jnp.where(positive, x, 1))), 0)


# --------------------------------------------------------------------------- Kakimoto


def kakimoto_sigmoid(
    x: Float[ArrayLike, "*shape"],
    D: float | Float[ArrayLike, ""] = 640.0,
    k: float | Float[ArrayLike, ""] = 20.0,
    g: float | Float[ArrayLike, ""] = 0.465,
) -> Float[Array, "*shape"]:
    """The sigmoid tone curve of Kakimoto et al. (eq. 7): ``D (x^g + 1) / (x^g + k)``.

    The result is in the paper's **display units**, frame-buffer values whose
    displayable range is [0, 255] (`DISPLAY_MAX`). The curve rises monotonically
    (for k > 1) from ``D / k`` at x = 0 (32 with the defaults: a black level, not
    zero) towards ``D`` as x → ∞; with D = 640 > 255 the top of the curve is
    beyond the display and saturates once clipped, which `display_to_unit` does.
    The output spans a ratio of ``k`` (the paper's prose speaks of k²; this is the
    formula as printed). Negative inputs count as 0.

    **Arguments:**

    - `x`: input luminance (the FFT intensity or image value, scaled as the
      caller chooses; with the defaults, display white 255 is reached at x ≈ 194).
    - `D`: upper limit of the output (display units), > 0. Paper: 640.
    - `k`: ratio of the upper limit to the value at x = 0, > 1. Paper: 20.
    - `g`: exponent setting, with `k`, the steepest slope, > 0. Paper: 0.465.

    **Returns:** display values, same shape as `x`.

    **Example:**

    ```python
    kakimoto_sigmoid(1.0)   # 640 * 2 / 21 ≈ 60.95
    ```
    """
    for name, value in (("D", D), ("k", k), ("g", g)):
        check_positive(f"kakimoto_sigmoid {name}", value)
    x = as_float(x)
    xg = _safe_pow(jnp.maximum(x, 0), jnp.asarray(g, x.dtype))
    return (xg + 1) / (xg + k) * D


def kakimoto_sigmoid_inverse(
    y: Float[ArrayLike, "*shape"],
    D: float | Float[ArrayLike, ""] = 640.0,
    k: float | Float[ArrayLike, ""] = 20.0,
    g: float | Float[ArrayLike, ""] = 0.465,
) -> Float[Array, "*shape"]:
    """The input `x` at which `kakimoto_sigmoid` reaches the display value `y`.

    ``x = ((k y / D - 1) / (1 - y / D)) ** (1 / g)``, defined for
    ``D / k <= y < D``; outside that range the result is NaN.

    ```python
    kakimoto_sigmoid_inverse(255.0)   # ≈ 194: the input that just reaches display white
    ```
    """
    y = as_float(y)
    r = y / D
    base = (k * r - 1) / (1 - r)
    valid = (base >= 0) & (r < 1)
    return jnp.where(valid, jnp.where(valid, base, 1) ** (1 / g), jnp.nan)


def display_to_unit(
    y: Float[ArrayLike, "*shape"], display_max: float = DISPLAY_MAX
) -> Float[Array, "*shape"]:
    """Display units (0 to `display_max`, 255 for the paper) → [0, 1], clipped.

    ```python
    display_to_unit(kakimoto_sigmoid(1e6))   # 1.0: beyond 255 saturates
    ```
    """
    return jnp.clip(as_float(y) / display_max, 0, 1)


def kakimoto_tonemap(
    image: Float[ArrayLike, "h w *c"],
    scale: float | Float[ArrayLike, ""] = 1.0,
    D: float | Float[ArrayLike, ""] = 640.0,
    k: float | Float[ArrayLike, ""] = 20.0,
    g: float | Float[ArrayLike, ""] = 0.465,
) -> Float[Array, "h w *c"]:
    """Kakimoto's sigmoid applied to each channel, normalised to [0, 1] (the `"kakimoto"` map).

    ``display_to_unit(kakimoto_sigmoid(scale * image, D, k, g))``: as in the
    paper the curve itself is the display encoding (no further gamma) and RGB
    channels are mapped independently. `scale` converts the image's units
    (cd/m^2) to the curve's input; pixels of luminance ``194 / scale`` reach white
    with the defaults, and black pixels show the curve's floor ``D / k / 255``
    (0.125 with the defaults).

    **Example:**

    ```python
    png = kakimoto_tonemap(hdr, scale=0.05)   # 3880 cd/m^2 → white
    ```
    """
    check_positive("kakimoto scale", scale)
    image = as_float(image)
    return display_to_unit(kakimoto_sigmoid(image * scale, D, k, g))


class GlareLayers(NamedTuple):
    """A glare PSF split into its central spot and the glare around it.

    **Fields:**

    - `spot`: the part of the PSF above `clip_level` (zero outside the spot).
    - `glare`: the PSF clipped at `clip_level`, ``min(psf, clip_level)``: the
      diffraction pattern with the spot flattened to a plateau (no hole).
    - `clip_level`: scalar, the brightest PSF value (over all channels) outside
      the spot radius.

    ``spot + glare == psf`` (to rounding), so either layer can be rendered in linear
    units (e.g. billboards of `glare` around sources drawn by the scene itself)
    and the two recombined without loss.
    """

    spot: Float[Array, "h w *c"]
    glare: Float[Array, "h w *c"]
    clip_level: Float[Array, ""]


def kakimoto_glare_layers(psf: Float[ArrayLike, "h w *c"], spot_radius_px: float) -> GlareLayers:
    """Split a PSF into a central-spot layer and a glare layer (Kakimoto sec. 3.3).

    The diffraction pattern is orders of magnitude fainter than the spot at its
    centre, so the paper keeps the spot on its own layer and tone-maps the glare
    after clipping the input. Here the clip level is the largest PSF value
    (over all channels, so colours keep their ratios) among pixels farther than
    `spot_radius_px` from the centre `(h // 2, w // 2)`; everything above it is
    the spot.

    **Arguments:**

    - `psf`: `(h, w)` or `(h, w, C)`, linear.
    - `spot_radius_px`: radius (pixels, >= 0) of the region treated as the spot,
      e.g. the first dark ring of the Airy pattern. Must leave pixels outside.

    **Returns:** `GlareLayers(spot, glare, clip_level)`.

    **Example:**

    ```python
    layers = kakimoto_glare_layers(psf, 3.0)   # layers.spot + layers.glare ≈ psf
    ```
    """
    psf = as_float(psf)
    if psf.ndim not in (2, 3):
        raise InputDataError(f"psf must have shape (h, w) or (h, w, C); got {psf.shape}")
    h, w = psf.shape[:2]
    radius = float(spot_radius_px)
    yy = jnp.arange(h)[:, None] - h // 2
    xx = jnp.arange(w)[None, :] - w // 2
    outside = (yy**2 + xx**2) > radius**2
    if not radius >= 0 or not bool(jnp.any(outside)):
        raise PhysicsRangeError(
            f"spot_radius_px must be >= 0 and leave pixels outside the spot of a {h}x{w} PSF; "
            f"got {spot_radius_px!r}"
        )
    mask = outside if psf.ndim == 2 else outside[..., None]
    clip_level = jnp.max(jnp.where(mask, psf, -jnp.inf))
    glare = jnp.minimum(psf, clip_level)
    return GlareLayers(psf - glare, glare, clip_level)


def kakimoto_glare_image(
    psf: Float[ArrayLike, "h w *c"],
    spot_radius_px: float,
    D: float | Float[ArrayLike, ""] = 640.0,
    k: float | Float[ArrayLike, ""] = 20.0,
    g: float | Float[ArrayLike, ""] = 0.465,
) -> Float[Array, "h w *c"]:
    """The paper's displayed glare image I_p: spot clipped off, glare expanded and tone-mapped.

    The glare layer of `kakimoto_glare_layers` is expanded so that its clip level
    lands where the sigmoid reaches display white (255), then mapped by eq. 7 and
    normalised to [0, 1]. The whole dynamic range of the display thus goes to the
    diffraction pattern, and the spot, which the clip flattened to that level,
    composes on top as saturated white. Independent of the PSF's overall scale.

    **Returns:** display values in [0, 1], same shape as `psf`; the floor is
    ``D / k / 255``.

    **Example:**

    ```python
    write_png("glare.png", kakimoto_glare_image(psf_rgb, 3.0))
    ```
    """
    layers = kakimoto_glare_layers(psf, spot_radius_px)
    white = kakimoto_sigmoid_inverse(DISPLAY_MAX, D, k, g).astype(layers.glare.dtype)
    tiny = jnp.finfo(layers.glare.dtype).tiny
    x = layers.glare / jnp.maximum(layers.clip_level, tiny) * white
    return display_to_unit(kakimoto_sigmoid(x, D, k, g))


def kakimoto_scene_scale(
    psf: Float[ArrayLike, "h w *c"],
    spot_radius_px: float,
    light_value: float | Float[ArrayLike, ""],
    D: float | Float[ArrayLike, ""] = 640.0,
    k: float | Float[ArrayLike, ""] = 20.0,
    g: float | Float[ArrayLike, ""] = 0.465,
) -> Float[Array, ""]:
    """The `scale` of `kakimoto_tonemap` that treats the central spot as its own layer.

    A scene rendered with a glare PSF holds, around each light of value ``v``,
    ``v * psf``: a spot orders of magnitude brighter than the diffraction pattern.
    Exposing for the spot would leave the glare black, so, as for a single PSF in
    `kakimoto_glare_image`, the exposure is set by the glare layer: the plateau of
    the brightest light's glare, ``light_value * clip_level``, lands on display
    white, and the spot above it saturates (it composes on top as white). A light
    of value ``v`` then shows ``kakimoto_glare_image(psf)`` scaled by ``v / light_value``.

    **Arguments:**

    - `psf`: the PSF at the scene's pixel scale, `(h, w)` or `(h, w, C)`.
    - `spot_radius_px`: the spot's radius in scene pixels (see `kakimoto_glare_layers`).
    - `light_value`: the brightest light's value in the scene's units (> 0).
    - `D`, `k`, `g`: the sigmoid's parameters, as for `kakimoto_sigmoid`.

    **Example:**

    ```python
    scale = kakimoto_scene_scale(psf, 1.5, float(scene.max()))
    png = kakimoto_tonemap(rendered, scale)
    ```
    """
    check_positive("light_value", light_value)
    clip_level = kakimoto_glare_layers(psf, spot_radius_px).clip_level
    white = kakimoto_sigmoid_inverse(DISPLAY_MAX, D, k, g).astype(clip_level.dtype)
    return white / (jnp.maximum(clip_level, jnp.finfo(clip_level.dtype).tiny) * light_value)


# --------------------------------------------------------------------------- Reinhard


def log_average_luminance(
    image: Float[ArrayLike, "h w *c"], delta: float = 1e-6
) -> Float[Array, ""]:
    """``exp(mean(log(delta + L)))``, the geometric mean luminance (Reinhard eq. 1).

    `delta` (image units) keeps black pixels from sending the mean to −∞. Negative
    luminance (out-of-gamut colours of a spectral PSF can have it) counts as black.
    """
    return jnp.exp(jnp.mean(jnp.log(delta + jnp.maximum(luminance(as_float(image)), 0.0))))


def reinhard_global(
    image: Float[ArrayLike, "h w *c"],
    key: float | Float[ArrayLike, ""] = 0.18,
    white: float | Float[ArrayLike, ""] | None = None,
    *,
    delta: float = 1e-6,
) -> Float[Array, "h w *c"]:
    """Reinhard et al. 2002, global operator, on luminance; colour scaled by the same ratio.

    With ``L`` the Rec. 709 luminance and ``L_avg`` its log-average
    (`log_average_luminance`): ``L_m = key L / L_avg``, then
    ``L_d = L_m / (1 + L_m)`` or, with a white point,
    ``L_d = L_m (1 + L_m / L_white²) / (1 + L_m)`` where ``L_white`` is `white`
    scaled like ``L``. Each pixel's channels are multiplied by ``L_d / L`` (hue
    and saturation kept).

    **Arguments:**

    - `image`: `(H, W)` or `(H, W, 3)` linear values (cd/m^2).
    - `key`: the display luminance the log-average maps to before compression (> 0).
    - `white`: the smallest luminance **in the image's units** that maps to
      display white (L_d = 1), or `None` for the plain ``L / (1 + L)`` curve,
      which never reaches 1.
    - `delta`: see `log_average_luminance`.

    **Returns:** *linear* display values, same shape; luminance is below 1
    except above `white` (burn-out, not clipped here); apply `srgb_encode` (or
    use `reinhard_display`) before writing 8-bit files.

    **Example:**

    ```python
    ld = reinhard_global(hdr, key=0.18, white=float(hdr.max()))
    ```
    """
    check_positive("reinhard key", key)
    if white is not None:
        check_positive("reinhard white", white, "(image units)")
    image = as_float(image)
    lum = jnp.maximum(luminance(image), 0.0)  # negative (out-of-gamut) luminance: black
    gain = key / log_average_luminance(image, delta)
    lm = gain * lum
    # L_d / L computed without dividing by L, so black pixels give 0, not NaN.
    ratio = gain / (1 + lm)
    if white is not None:
        ratio = ratio * (1 + lm / (gain * white) ** 2)
    return image * (ratio if image.ndim == 2 else ratio[..., None])


def reinhard_display(
    image: Float[ArrayLike, "h w *c"],
    key: float | Float[ArrayLike, ""] = 0.18,
    white: float | Float[ArrayLike, ""] | None = None,
    delta: float = 1e-6,
) -> Float[Array, "h w *c"]:
    """`reinhard_global`, clipped to [0, 1] and sRGB-encoded (the `"reinhard"` map)."""
    return srgb_encode(jnp.clip(reinhard_global(image, key, white, delta=delta), 0, 1))


# --------------------------------------------------------------------------- gamma / sRGB


def srgb_encode(linear: Float[ArrayLike, "*shape"]) -> Float[Array, "*shape"]:
    """The sRGB transfer function (IEC 61966-2-1) in `jnp`, not clipped.

    Same curve as the numpy `invglare.files.encode_srgb` (which stays numpy so that
    file I/O does not import JAX); this one is traceable and differentiable.

    ```python
    srgb_encode(0.18)   # ≈ 0.4614
    ```
    """
    x = as_float(linear)
    power = 1.055 * jnp.maximum(x, 0.0031308) ** (1 / 2.4) - 0.055
    return jnp.where(x <= 0.0031308, 12.92 * x, power)


def srgb_display(
    image: Float[ArrayLike, "*shape"], exposure: float | Float[ArrayLike, ""] = 1.0
) -> Float[Array, "*shape"]:
    """``srgb_encode(clip(exposure * image, 0, 1))`` (the `"srgb"` map).

    `exposure` (1 / image units) maps the image's values to display linear
    light, where 1 is display white.
    """
    check_positive("exposure", exposure)
    return srgb_encode(jnp.clip(as_float(image) * exposure, 0, 1))


def exposure_gamma(
    image: Float[ArrayLike, "*shape"],
    exposure: float | Float[ArrayLike, ""] = 1.0,
    gamma: float | Float[ArrayLike, ""] = 2.2,
) -> Float[Array, "*shape"]:
    """``clip(exposure * image, 0, 1) ** (1 / gamma)``, a plain power-law display encoding.

    **Arguments:**

    - `image`: linear values.
    - `exposure`: multiplier (1 / image units) taking values to [0, 1], > 0.
    - `gamma`: display gamma, > 0 (2.2 for a typical monitor).

    **Example:**

    ```python
    exposure_gamma(0.5, 1.0, 2.2)   # 0.5 ** (1 / 2.2) ≈ 0.7297
    ```
    """
    check_positive("exposure", exposure)
    check_positive("gamma", gamma)
    x = jnp.clip(as_float(image) * exposure, 0, 1)
    return _safe_pow(x, 1 / jnp.asarray(gamma, x.dtype))


# --------------------------------------------------------------------------- registry

#: Tone maps by name: linear image + keyword parameters → display values in [0, 1].
TONEMAPS: dict[str, Callable[..., Array]] = {
    "kakimoto": kakimoto_tonemap,
    "reinhard": reinhard_display,
    "gamma": exposure_gamma,
    "srgb": srgb_display,
}


def tonemap(image: Float[ArrayLike, "h w *c"], name: str, **params) -> Float[Array, "h w *c"]:
    """Tone-map a linear HDR image with the operator `name` of `TONEMAPS`.

    **Raises:** `ConfigError` for an unknown name (listing the valid ones) or
    a parameter the operator does not take (listing the ones it does).

    ```python
    png = tonemap(hdr, "reinhard", key=0.18)
    ```
    """
    fn = TONEMAPS.get(name) if isinstance(name, str) else None
    if fn is None:
        raise ConfigError(f"unknown tone map {name!r}; valid names: {', '.join(TONEMAPS)}")
    accepted = list(inspect.signature(fn).parameters)[1:]
    unknown = sorted(set(params) - set(accepted))
    if unknown:
        raise ConfigError(
            f"tone map {name!r} has no parameter(s) {', '.join(map(repr, unknown))}; "
            f"valid: {', '.join(accepted)}"
        )
    return fn(image, **params)
