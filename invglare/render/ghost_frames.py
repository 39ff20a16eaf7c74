"""Veiling glare (lens ghosts) rendered onto an HDR image.

Lens ghosts are not a shift-invariant PSF: as a light moves off the axis its ghosts
move along the line through the axis, and they grow or fade. So a veiling-glare
render is per light: the bright pixels of the frame (`bright_pixel_list`) are the
lights, each in the direction whose direct image is its pixel (the frame is the
model's screen, the sensor in units of the EFL: a pixel at ``s`` deg from the centre,
the optical axis, is the light at ``atan(s)``,
:func:`~invglare.models.veiling_ghosts.direction_of_screen_deg`), and
each adds the veiling image of :class:`~invglare.models.veiling.VeilingGlare` for its
own direction, scaled by its value. The light that went into ghosts leaves the
light's own pixel (its value is scaled by the model's direct fraction), so the
frame's total light is kept up to what the lens loses. Ghosts are achromatic here: a
colour pixel's channels all get the same ghost image.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from invglare.errors import InputDataError
from invglare.models.base import check_light_angle
from invglare.models.veiling import VeilingGlare
from invglare.models.veiling_ghosts import direction_of_screen_deg
from invglare.render.bright import BrightPixels, light_angles_deg


def render_ghosts(
    model: VeilingGlare,
    image: Float[ArrayLike, "h w *c"],
    bright: BrightPixels,
    pixel_scale_deg: float,
    batch_size: int = 16,
) -> Float[Array, "h w *c"]:
    """`image` with the ghosts of its listed bright pixels added.

    **Arguments:**

    - `model`: a veiling model built on the image's grid (``npix == image.shape[:2]``
      and ``pixel_scale_deg`` the image's), its axis at the image centre.
    - `image`: linear HDR ``(H, W)`` or ``(H, W, C)``.
    - `bright`: the lights, from :func:`~invglare.render.bright_pixel_list`.
    - `pixel_scale_deg`: the image's degrees per pixel.
    - `batch_size`: lights evaluated at once (memory: K images of H x W in all).

    **Example:**

    ```python
    bright = bright_pixel_list(scene, threshold=1000.0, max_count=32)
    out = render_ghosts(model, scene, bright, pixel_scale_deg=0.05)
    ```
    """
    image = jnp.asarray(image)
    shape = tuple(image.shape[:2])
    if tuple(model.npix) != shape or abs(model.pixel_scale_deg - pixel_scale_deg) > (
        1e-9 * pixel_scale_deg
    ):
        raise InputDataError(
            f"the veiling model's screen is {model.npix} px at {model.pixel_scale_deg} deg/px "
            f"but the image is {shape} px at {pixel_scale_deg} deg/px; build the model on the "
            "image's grid"
        )
    colour = image.ndim == 3
    values = bright.values if colour else bright.values[:, None]
    values = jnp.where(bright.valid[:, None], values, 0.0)
    angles = direction_of_screen_deg(light_angles_deg(bright, shape, pixel_scale_deg))
    check_light_angle(angles, batched=True)
    images = model.batch(angles, batch_size=batch_size)  # (K, H, W)
    ghosts = jnp.einsum("khw,kc->hwc", images, values.astype(images.dtype))
    direct = jax.vmap(model.direct_fraction)(angles)
    lost = (1.0 - direct)[:, None] * values
    img = image if colour else image[..., None]
    img = img.at[bright.rows, bright.cols].add(-lost.astype(image.dtype))
    out = img + ghosts.astype(image.dtype)
    return out if colour else out[..., 0]
