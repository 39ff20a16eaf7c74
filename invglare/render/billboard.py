"""Billboard compositing: a copy of the glare PSF stamped on every bright pixel.

This is the rendering scheme of Kakimoto et al. (sec. 4): instead of convolving
the whole image, the glare image is placed, centred, at each of a few
high-intensity pixels and multiplied by that pixel's value. With the same PSF
everywhere it is exactly the convolution of the bright-pixel image with the PSF
(`convolve_psf(bright_pixels(...), psf)`), but it costs `N * h * w` instead of a
full-frame FFT, and it allows a **different PSF per position** (the eyelash
silhouette shifts with the light direction, sec. 4.2-4.3): pass a bank of PSFs and
an index per billboard.

Billboards are accumulated with `lax.scan` on a canvas padded by the PSF size, so
memory stays one canvas whatever the number of billboards, and stamps that
overhang the frame are clipped rather than wrapped.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Int

from invglare.errors import InputDataError
from invglare.render.bright import BrightPixels

__all__ = ["add_billboards", "billboard_glare", "replace_with_billboards"]


def _bank_channels_first(psf: Array, per_position: bool) -> Array:
    """Return the PSF(s) as `(K, C, h, w)`."""
    bank = psf if per_position else psf[None]
    if bank.ndim == 3:
        return bank[:, None]
    if bank.ndim == 4:
        return jnp.moveaxis(bank, -1, 1)
    what = "(K, h, w) or (K, h, w, C)" if per_position else "(h, w) or (h, w, C)"
    raise InputDataError(f"psf must have shape {what}; got {psf.shape}")


def billboard_glare(
    bright: BrightPixels,
    psf: Float[ArrayLike, "*k h w *c"],
    shape: tuple[int, int],
    *,
    psf_index: Int[ArrayLike, " n"] | None = None,
) -> Float[Array, "H W *c"]:
    """The glare of a list of bright pixels: PSFs scaled by pixel value, centred on each.

    ``out[r + a - h // 2, c + b - w // 2] += value * psf[a, b]`` for every valid
    entry `(r, c, value)` of `bright`; what falls outside the `shape` frame is
    dropped. Entries that are invalid or lie outside the frame add nothing.

    **Arguments:**

    - `bright`: positions and values, e.g. from `bright_pixel_list`; `values` is
      `(N,)` or `(N, C)`.
    - `psf`: one PSF, `(h, w)` or `(h, w, C)`, energy per pixel, centre at
      `(h // 2, w // 2)`; or, with `psf_index`, a bank `(K, h, w)` / `(K, h, w, C)`.
    - `shape`: `(H, W)` of the output frame.
    - `psf_index`: optional int `(N,)`, the bank entry used by each billboard (a
      per-position PSF; `jnp.arange(N)` for one PSF per billboard).

    **Returns:** `(H, W)` when both `values` and the PSF are single-channel, else
    `(H, W, C)`.

    **Example:**

    ```python
    bp = bright_pixel_list(scene, 1e3, 64)
    glare = billboard_glare(bp, psf_rgb, scene.shape[:2])
    ```
    """
    psf = jnp.asarray(psf)
    values = jnp.asarray(bright.values)
    if not jnp.issubdtype(psf.dtype, jnp.floating):
        psf = psf.astype(jnp.result_type(float))
    dtype = jnp.result_type(psf.dtype, values.dtype)
    bank = _bank_channels_first(psf.astype(dtype), psf_index is not None)
    vals = values.astype(dtype)
    vals = vals[:, None] if vals.ndim == 1 else vals
    n = vals.shape[0]
    if vals.ndim != 2 or jnp.shape(bright.rows) != (n,) or jnp.shape(bright.cols) != (n,):
        raise InputDataError(
            f"bright pixels need rows, cols of shape (N,) and values (N,) or (N, C); got "
            f"{jnp.shape(bright.rows)}, {jnp.shape(bright.cols)}, {values.shape}"
        )
    _, cp, h, w = bank.shape
    cv = vals.shape[1]
    if cp != cv and 1 not in (cp, cv):
        raise InputDataError(
            f"bright-pixel values have {cv} channels but the PSF has {cp}; give a mono PSF "
            "or one with the values' channels"
        )
    c = max(cp, cv)
    hh, ww = (int(s) for s in shape)
    if psf_index is None:
        index = jnp.zeros(n, jnp.int32)
    else:
        index = jnp.asarray(psf_index, jnp.int32)
        if index.shape != (n,):
            raise InputDataError(f"psf_index must have shape ({n},); got {index.shape}")

    rows = jnp.asarray(bright.rows, jnp.int32)
    cols = jnp.asarray(bright.cols, jnp.int32)
    inside = (rows >= 0) & (rows < hh) & (cols >= 0) & (cols < ww)
    # Out-of-frame entries are zeroed (dynamic_slice would otherwise clamp them back in).
    keep = (jnp.asarray(bright.valid) & inside).astype(dtype)
    rows, cols = jnp.where(inside, rows, 0), jnp.where(inside, cols, 0)

    def stamp(canvas, item):
        r, col, v, k, idx = item
        contrib = jnp.broadcast_to(bank[idx] * (v * k)[:, None, None], (c, h, w))
        # On the canvas padded by the PSF's top-left half, the stamp starts at (r, col).
        start = (jnp.zeros((), jnp.int32), r, col)
        window = jax.lax.dynamic_slice(canvas, start, (c, h, w))
        return jax.lax.dynamic_update_slice(canvas, window + contrib, start), None

    canvas = jnp.zeros((c, hh + h - 1, ww + w - 1), dtype)
    canvas, _ = jax.lax.scan(stamp, canvas, (rows, cols, vals, keep, index))
    out = canvas[:, h // 2 : h // 2 + hh, w // 2 : w // 2 + ww]
    psf_is_mono = psf.ndim == (2 if psf_index is None else 3)
    if values.ndim == 1 and psf_is_mono:
        return out[0]
    return jnp.moveaxis(out, 0, -1)


def add_billboards(
    image: Float[ArrayLike, "H W *c"],
    bright: BrightPixels,
    psf: Float[ArrayLike, "*k h w *c"],
    *,
    psf_index: Int[ArrayLike, " n"] | None = None,
) -> Float[Array, "H W *c"]:
    """`image` plus the billboard glare of `bright` (see `billboard_glare`).

    The bright pixels themselves stay in the image: with a PSF that sums to 1
    this adds each source's energy a second time, spread as glare. To
    redistribute instead, use `replace_with_billboards`, or a PSF whose central
    spot has been taken out (`invglare.render.kakimoto_glare_layers`).

    **Example:**

    ```python
    out = add_billboards(scene, bright_pixel_list(scene, 1e3, 64), psf_rgb)
    ```
    """
    image = jnp.asarray(image)
    glare = billboard_glare(bright, psf, image.shape[:2], psf_index=psf_index)
    if image.ndim == 2 and glare.ndim == 3:
        image = image[..., None]
    return image + glare


def replace_with_billboards(
    image: Float[ArrayLike, "H W *c"],
    bright: BrightPixels,
    psf: Float[ArrayLike, "*k h w *c"],
    *,
    psf_index: Int[ArrayLike, " n"] | None = None,
) -> Float[Array, "H W *c"]:
    """`image` with each listed bright pixel replaced by its billboard (energy kept).

    The valid pixels of `bright` are taken out of the image and put back spread by
    the PSF (which sums to 1: the central spot returns most of the light to its
    pixel). Bright pixels that did not make the list stay as they are.

    **Example:**

    ```python
    out = replace_with_billboards(scene, bright_pixel_list(scene, 1e3, 64), psf_rgb)
    ```
    """
    image = jnp.asarray(image)
    listed = (
        jnp.zeros(image.shape[:2], image.dtype)
        .at[jnp.asarray(bright.rows), jnp.asarray(bright.cols)]
        .max(jnp.asarray(bright.valid).astype(image.dtype))
    )
    keep = 1.0 - (listed if image.ndim == 2 else listed[..., None])
    return add_billboards(image * keep, bright, psf, psf_index=psf_index)
