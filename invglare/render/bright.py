"""Bright-pixel extraction: the light sources and highlights that carry the glare.

Glare is only visible around pixels far brighter than their surroundings, so the
render pipeline first separates them from the rest of the image. The threshold is
in the image's **own linear units**: cd/m^2 when the scene is photometrically
calibrated (the bundled scenes are), otherwise whatever the HDR file holds. Colour
images are thresholded on their Rec. 709 luminance, so a pixel is kept or removed
whole (all channels together) and its colour is preserved.

Two forms:

- `bright_pixels` keeps the image layout (everything below the threshold set to
  zero), the input of FFT convolution;
- `bright_pixel_list` returns a fixed number of the brightest pixels as arrays of
  positions and values, the input of billboard compositing. `max_count` is static,
  so the function jits and vmaps; unused slots are flagged invalid and hold zeros.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from invglare.errors import InputDataError, PhysicsRangeError

__all__ = [
    "REC709_WEIGHTS",
    "BrightPixels",
    "bright_pixel_list",
    "bright_pixels",
    "light_angles_deg",
    "luminance",
]

#: Rec. 709 / sRGB luminance weights of linear R, G, B.
REC709_WEIGHTS = (0.2126, 0.7152, 0.0722)


class BrightPixels(NamedTuple):
    """A fixed-size list of bright pixels, as returned by `bright_pixel_list`.

    **Fields** (`N` = `max_count`):

    - `rows`, `cols`: int32 `(N,)` pixel indices (row 0 is the top row).
    - `values`: `(N,)` for a single-channel image, `(N, C)` for a colour one; the
      pixel values in the image's units, zero where `valid` is false.
    - `valid`: bool `(N,)`, true for slots that hold a pixel above the threshold.
    - `n_above`: int32 scalar, how many pixels of the image are above the
      threshold; more than `N` means the list was truncated to the brightest `N`.
    """

    rows: Int[Array, " n"]
    cols: Int[Array, " n"]
    values: Float[Array, " n *c"]
    valid: Bool[Array, " n"]
    n_above: Int[Array, ""]


def _as_image(image: ArrayLike) -> Array:
    image = jnp.asarray(image)
    if image.ndim not in (2, 3) or image.shape[0] < 1 or image.shape[1] < 1:
        raise InputDataError(
            f"image must have shape (H, W) or (H, W, C) with H, W >= 1; got {image.shape}"
        )
    if not jnp.issubdtype(image.dtype, jnp.floating):
        image = image.astype(jnp.result_type(float))
    return image


def luminance(image: Float[ArrayLike, "h w *c"]) -> Float[Array, "h w"]:
    """Rec. 709 luminance of a linear RGB image; a single-channel image is its own luminance.

    **Arguments:**

    - `image`: `(H, W)`, `(H, W, 1)` or `(H, W, 3)` linear values.

    **Returns:** `(H, W)` luminance in the image's units.

    **Example:**

    ```python
    luminance(jnp.ones((4, 4, 3)))   # all ones: the weights sum to 1
    ```
    """
    image = _as_image(image)
    if image.ndim == 2:
        return image
    if image.shape[-1] == 1:
        return image[..., 0]
    if image.shape[-1] != 3:
        raise InputDataError(
            f"luminance needs a 1- or 3-channel image; got {image.shape[-1]} channels "
            f"(shape {image.shape})"
        )
    return image @ jnp.asarray(REC709_WEIGHTS, dtype=image.dtype)


def _check_threshold(threshold) -> None:
    if isinstance(threshold, jax.core.Tracer):
        return
    t = np.asarray(threshold, dtype=float)
    if t.shape != () or not np.isfinite(t) or t < 0:
        raise PhysicsRangeError(
            f"threshold must be one finite number >= 0 in the image's units (cd/m^2 for a "
            f"calibrated scene); got {threshold!r}"
        )


def bright_pixels(
    image: Float[ArrayLike, "h w *c"],
    threshold: float | Float[ArrayLike, ""],
    *,
    softness: float | None = None,
) -> Float[Array, "h w *c"]:
    """The image with every pixel whose luminance is below `threshold` removed.

    Pixels at or above the threshold are kept whole (not reduced by the
    threshold): in the paper's pipeline each bright pixel emits glare in
    proportion to its full value.

    **Arguments:**

    - `image`: `(H, W)` or `(H, W, C)` linear HDR values (C = 1 or 3).
    - `threshold`: luminance in the image's units (cd/m^2 for a calibrated
      scene), >= 0.
    - `softness`: `None` (default) for a hard cut. A positive number makes the
      cut a logistic step in *log* luminance, ``sigmoid(ln(L / threshold) /
      softness)``, so the result is differentiable in `threshold` and in the
      pixel values; e.g. `0.1` spreads the transition over about ±10 % of the
      threshold. Log units because HDR values span decades.

    **Returns:** the same shape and dtype as `image`.

    **Example:**

    ```python
    lamps = bright_pixels(scene, 1000.0)   # keep pixels of >= 1000 cd/m^2
    ```
    """
    image = _as_image(image)
    _check_threshold(threshold)
    lum = luminance(image)
    threshold = jnp.asarray(threshold, dtype=image.dtype)
    if softness is None:
        weight = (lum >= threshold).astype(image.dtype)
    else:
        if not softness > 0:
            raise PhysicsRangeError(f"softness must be > 0 (log-luminance units); got {softness}")
        tiny = jnp.finfo(image.dtype).tiny
        # Clamping keeps log finite at L = 0 (and its gradient zero there, not NaN).
        log_ratio = jnp.log(jnp.maximum(lum, tiny)) - jnp.log(jnp.maximum(threshold, tiny))
        weight = jax.nn.sigmoid(log_ratio / softness)
    return image * (weight if image.ndim == 2 else weight[..., None])


def bright_pixel_list(
    image: Float[ArrayLike, "h w *c"],
    threshold: float | Float[ArrayLike, ""],
    max_count: int,
) -> BrightPixels:
    """The `max_count` brightest pixels above `threshold`, as fixed-size arrays.

    Pixels are ranked by luminance with `jax.lax.top_k` (ties: lower flat index
    first). Slots beyond the pixels above the threshold are marked invalid and
    their `values` are zero, so they add nothing when composited.

    **Arguments:**

    - `image`: `(H, W)` or `(H, W, C)` linear HDR values.
    - `threshold`: luminance in the image's units (cd/m^2 when calibrated), >= 0.
    - `max_count`: number of slots (static Python int, 1 <= max_count <= H * W).

    **Returns:** a `BrightPixels` tuple, brightest first. Compare `n_above` with
    `max_count` to see whether bright pixels were left out.

    **Example:**

    ```python
    bp = jax.jit(bright_pixel_list, static_argnums=2)(scene, 1000.0, 64)
    ```
    """
    image = _as_image(image)
    _check_threshold(threshold)
    h, w = image.shape[:2]
    if not isinstance(max_count, int | np.integer) or not 1 <= max_count <= h * w:
        raise InputDataError(
            f"max_count must be an int between 1 and the number of pixels {h * w}; "
            f"got {max_count!r}"
        )
    lum = luminance(image).reshape(-1)
    top, flat = jax.lax.top_k(lum, int(max_count))
    valid = top >= jnp.asarray(threshold, dtype=image.dtype)
    rows, cols = (flat // w).astype(jnp.int32), (flat % w).astype(jnp.int32)
    values = image.reshape(h * w, -1)[flat] if image.ndim == 3 else lum[flat]
    mask = valid if values.ndim == 1 else valid[:, None]
    values = jnp.where(mask, values, jnp.zeros((), values.dtype))
    n_above = jnp.sum(lum >= jnp.asarray(threshold, dtype=image.dtype), dtype=jnp.int32)
    return BrightPixels(rows, cols, values, valid, n_above)


def light_angles_deg(
    bright: BrightPixels, shape: tuple[int, int], pixel_scale_deg: float
) -> Float[Array, "n 2"]:
    """``(n, 2)`` (x, y) angles (deg) of the listed pixels from the centre pixel.

    The centre pixel ``(H // 2, W // 2)`` is the optical axis; x grows with the
    column and y with the row, as the coordinates of `invglare._core.grids`
    (so a model's PSF for the light at that angle matches the frame's orientation):
    in the frame as an image file shows it (row 0 at the top) +y points down. The
    offsets are pixel offsets times the scale, the small-angle reading of the frame;
    a veiling model, whose screen is its sensor, turns them into directions with
    :func:`~invglare.models.veiling_ghosts.direction_of_screen_deg`.

    **Example:**

    ```python
    angles = light_angles_deg(bright_pixel_list(scene, 1e3, 8), scene.shape[:2], 0.05)
    ```
    """
    h, w = shape
    x = (jnp.asarray(bright.cols) - w // 2).astype(jnp.float32) * pixel_scale_deg
    y = (jnp.asarray(bright.rows) - h // 2).astype(jnp.float32) * pixel_scale_deg
    return jnp.stack([x, y], axis=-1)
