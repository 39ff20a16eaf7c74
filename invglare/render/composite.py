"""Kakimoto et al.'s compositing: tone-mapped glare billboards blended onto the LDR render.

Sec. 3.3-4.1 of the paper: each glare image is tone-mapped on its own, its central spot
on a separate layer and the diffraction pattern expanded into the sigmoid's range
(:func:`~invglare.render.tonemap.kakimoto_glare_image`, eq. 6-7), and stored as a
billboard texture; the frame is rendered twice, once in low dynamic range (the picture
the viewer sees) and once for its high-intensity pixels; at each of those a translucent
billboard of the glare texture, its intensity multiplied by the pixel's value, is blended
onto the low-dynamic-range picture.

Here (:func:`kakimoto_composite`):

- the low-dynamic-range picture is the scene under any tone map (`ldr`, in [0, 1]);
- the texture is the sigmoid-mapped glare with the sigmoid's floor ``D / k`` (32 of 255
  with the paper's numbers) taken off and the rest stretched back to [0, 1]
  (:func:`kakimoto_billboard_texture`), so a glare that is zero adds nothing and black
  stays black: the paper's billboards are translucent, their dark surround does not grey
  the picture;
- each light's billboard is scaled by its pixel's value over the brightest listed light's
  luminance (per channel: a red lamp gives red glare) times `gain`, added onto the
  picture and the sum clipped to [0, 1]. Overlapping lights add *after* each was
  tone-mapped, as billboards do, not before one compression of the whole frame.

The other way invglare offers (``invglare render --mode billboard --tonemap kakimoto``)
stamps linear PSFs into the HDR frame and then maps the whole frame by the sigmoid: a
tone map of the glare-added scene, which lifts every black pixel to the sigmoid's floor
and compresses overlapping lights together.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Int

from invglare._core.checks import as_float
from invglare._core.grids import check_positive
from invglare.errors import InputDataError
from invglare.render.billboard import billboard_glare
from invglare.render.bright import REC709_WEIGHTS, BrightPixels
from invglare.render.tonemap import DISPLAY_MAX, kakimoto_glare_image, kakimoto_sigmoid

__all__ = ["kakimoto_billboard_texture", "kakimoto_composite"]


def kakimoto_billboard_texture(
    psf: Float[ArrayLike, "h w *c"],
    spot_radius_px: float,
    D: float = 640.0,
    k: float = 20.0,
    g: float = 0.465,
) -> Float[Array, "h w *c"]:
    """The paper's glare texture ``I_p`` (eq. 6-7) with the sigmoid's floor taken off.

    ``(kakimoto_glare_image(psf) - f) / (1 - f)``, ``f = sig(0) / 255 = D / (k 255)``,
    clipped at 0: 0 where the glare is 0, 1 where the clipped glare layer reaches display
    white. Independent of the PSF's scale.

    **Example:**

    ```python
    texture = kakimoto_billboard_texture(psf_rgb, spot_radius_px=1.5)
    ```
    """
    floor = kakimoto_sigmoid(0.0, D, k, g) / DISPLAY_MAX
    image = kakimoto_glare_image(psf, spot_radius_px, D, k, g)
    return jnp.clip((image - floor) / (1.0 - floor), 0.0, 1.0)


def kakimoto_composite(
    ldr: Float[ArrayLike, "H W *c"],
    bright: BrightPixels,
    psf: Float[ArrayLike, "*k h w *c"],
    spot_radius_px: float,
    *,
    psf_index: Int[ArrayLike, " n"] | None = None,
    gain: float = 1.0,
    D: float = 640.0,
    k: float = 20.0,
    g: float = 0.465,
) -> Float[Array, "H W *c"]:
    """The low-dynamic-range picture with a glare billboard blended on at each bright pixel.

    **Arguments:**

    - `ldr`: the picture the viewer sees, display values in [0, 1] (the scene under a
      tone map), ``(H, W)`` or ``(H, W, C)``.
    - `bright`: the high-intensity pixels and their linear values (`bright_pixel_list`).
    - `psf`: the glare PSF at the picture's pixel scale, ``(h, w)`` or ``(h, w, C)``; or,
      with `psf_index`, one per position ``(K, h, w[, C])`` (the lashes moving with the
      light, sec. 4.2-4.3).
    - `spot_radius_px`: the central spot's radius in the picture's pixels (it is its
      own layer, sec. 3.3).
    - `psf_index`: the bank entry of each bright pixel.
    - `gain`: the billboards' opacity (1: the brightest light's glare plateau reaches
      white).
    - `D`, `k`, `g`: the sigmoid's parameters (the paper's 640, 20, 0.465).

    **Returns:** display values in [0, 1], the shape of `ldr` (channels of the PSF if
    `ldr` is grey and the PSF colour).

    **Example:**

    ```python
    ldr = tonemap(scene, "reinhard")
    out = kakimoto_composite(ldr, bright_pixel_list(scene, 1e3, 64), psf_rgb, 1.5)
    ```
    """
    check_positive("kakimoto composite gain", gain)
    ldr = as_float(ldr)
    psf = as_float(psf)

    def texture(p):
        return kakimoto_billboard_texture(p, spot_radius_px, D, k, g)

    textures = texture(psf) if psf_index is None else jax.vmap(texture)(psf)
    values = as_float(bright.values)
    if values.ndim == 1:
        lum = values
    elif values.shape[-1] == 3:
        lum = values @ jnp.asarray(REC709_WEIGHTS, values.dtype)
    else:
        lum = jnp.mean(values, axis=-1)
    brightest = jnp.max(jnp.where(jnp.asarray(bright.valid), lum, 0.0))
    if not bool(brightest > 0):
        raise InputDataError("no bright pixel with a positive value to put glare on")
    scaled = bright._replace(values=values * (gain / brightest))
    glare = billboard_glare(scaled, textures, ldr.shape[:2], psf_index=psf_index)
    if ldr.ndim == 2 and glare.ndim == 3:
        ldr = ldr[..., None]
    return jnp.clip(ldr + glare, 0.0, 1.0)
