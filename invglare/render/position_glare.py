"""Position-dependent glare on an HDR frame: every light its own PSF (Kakimoto eq. 3).

With ``masking="position"`` the eyelash silhouette slides over the pupil as the
light's direction changes (Kakimoto et al., sec. 4.2-4.3), so a frame's glare is no
convolution. Here the bright pixels of the frame are the lights, each at the angle
of its pixel from the centre (:func:`~invglare.render.bright.light_angles_deg`);
their PSFs come from :meth:`KakimotoGlare.batch` a few at a time, are resampled
(energy kept) to the frame's pixel scale, and are stamped as billboards with one
PSF per billboard. A fixed-mask model gives every light the same PSF, so the
result equals the single-PSF billboard render.

PSFs are unit-energy, as everywhere in invglare: a light half hidden behind a lash
is not dimmed (:meth:`KakimotoGlare.transmitted_fraction` gives the factor for a
renderer that wants it).
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from invglare._core.grids import check_positive
from invglare.errors import InputDataError
from invglare.render.billboard import replace_with_billboards
from invglare.render.bright import BrightPixels, light_angles_deg
from invglare.render.convolve import resample_psf

if TYPE_CHECKING:
    from invglare.models.base import AbstractGlareModel

__all__ = ["position_psf_bank", "psf_npix_at_scale", "render_position_glare"]

log = logging.getLogger("invglare")


def psf_npix_at_scale(
    psf_npix: int, from_scale_deg: float, to_scale_deg: float, max_npix: int
) -> int:
    """Odd size (px) covering the PSF's field at `to_scale_deg`, at most `max_npix`.

    **Example:**

    ```python
    psf_npix_at_scale(512, 0.005, 0.02, 1001)   # 129: 2.56 deg at 0.02 deg/px, made odd
    ```
    """
    field_deg = psf_npix * from_scale_deg
    npix = min(int(max_npix), max(3, math.ceil(field_deg / to_scale_deg)))
    return npix + 1 - npix % 2  # odd: the centre pixel stays centred


def position_psf_bank(
    model: AbstractGlareModel,
    light_angles_deg: Float[ArrayLike, "K 2"],
    pixel_scale_deg: float,
    npix: int,
    batch_size: int = 8,
    progress: bool | None = None,
) -> Float[Array, "K npix npix *c"]:
    """PSFs of `model` for each light direction, resampled to `pixel_scale_deg` per pixel.

    **Arguments:**

    - `model`: a :class:`~invglare.models.kakimoto.KakimotoGlare`.
    - `light_angles_deg`: ``(K, 2)`` (x, y) angles, as for :meth:`KakimotoGlare.batch`.
    - `pixel_scale_deg`: the frame's degrees per pixel.
    - `npix`: side of each resampled PSF (odd keeps the centre centred).
    - `batch_size`: PSFs computed per compiled call (memory: that many fields and
      PSFs at the model's own size).
    - `progress`: a tqdm bar over the lights (``None``: only on a terminal).

    **Returns:** ``(K, npix, npix)`` or ``(K, npix, npix, C)``, energy per pixel.

    **Example:**

    ```python
    bank = position_psf_bank(model, jnp.array([[0.0, 0.0], [4.0, -2.0]]), 0.02, 129)
    ```
    """
    from tqdm.auto import tqdm

    angles = np.asarray(light_angles_deg, dtype=float)
    if angles.ndim != 2 or angles.shape[-1] != 2:
        raise InputDataError(f"light_angles_deg must have shape (K, 2); got {angles.shape}")
    if angles.shape[0] == 0:
        raise InputDataError("light_angles_deg is empty: there is no light to give glare")
    check_positive("pixel_scale_deg", pixel_scale_deg, "deg")
    own_scale = float(model.pixel_scale_deg)
    batch = max(1, min(int(batch_size), angles.shape[0]))
    scales = (own_scale, float(pixel_scale_deg), int(npix))
    out = []
    disable = None if progress is None else not progress  # None: tqdm shows it on a terminal
    with tqdm(total=angles.shape[0], unit="light", desc="position PSFs", disable=disable) as bar:
        for start in range(0, angles.shape[0], batch):
            chunk = angles[start : start + batch]
            # The last batch is padded with on-axis lights so that it reuses the compiled call.
            padded = np.concatenate([chunk, np.zeros((batch - chunk.shape[0], 2))])
            psfs = _resampled_batch(model, jnp.asarray(padded, jnp.result_type(float)), *scales)
            out.append(psfs[: chunk.shape[0]])
            bar.update(chunk.shape[0])
    return jnp.concatenate(out)


@eqx.filter_jit
def _resampled_batch(model, angles, own_scale: float, scale: float, npix: int):
    # Module level, so that every call with the same model structure and scales
    # (Python numbers: static to filter_jit) reuses one compilation.
    return jax.vmap(lambda p: resample_psf(p, own_scale, scale, npix))(model.batch(angles))


def render_position_glare(
    model: AbstractGlareModel,
    image: Float[ArrayLike, "H W *c"],
    bright: BrightPixels,
    pixel_scale_deg: float,
    max_npix: int,
    batch_size: int = 8,
    progress: bool | None = None,
) -> Float[Array, "H W *c"]:
    """`image` with each listed light replaced by the glare of its own direction.

    **Arguments:**

    - `model`: a Kakimoto model (``masking="position"`` for glare that changes with
      the light's position; a fixed mask works too, at the cost of one PSF per light).
    - `image`: linear HDR ``(H, W)`` or ``(H, W, C)``; its centre pixel is the axis.
    - `bright`: the lights (:func:`~invglare.render.bright_pixel_list`); only valid
      entries get a PSF.
    - `pixel_scale_deg`: the image's degrees per pixel.
    - `max_npix`: largest PSF side after resampling.
    - `batch_size`, `progress`: as for :func:`position_psf_bank`.

    **Example:**

    ```python
    bright = bright_pixel_list(scene, 1e3, 32)
    out = render_position_glare(model, scene, bright, 0.02, 1025)
    ```
    """
    image = jnp.asarray(image)
    valid = np.flatnonzero(np.asarray(bright.valid))
    if valid.size == 0:
        log.warning("no pixel above the threshold: the image is returned without glare")
        return image
    lights = BrightPixels(*(jnp.asarray(f)[valid] for f in bright[:4]), bright.n_above)
    angles = light_angles_deg(lights, tuple(image.shape[:2]), pixel_scale_deg)
    beyond = float(jnp.max(jnp.abs(angles)))
    # A model meant for lights up to some angle (Kakimoto's scrolling obstacle) says so.
    max_angle = getattr(model, "max_light_angle_deg", math.inf)
    if not model.shift_invariant and beyond > max_angle:
        log.warning(
            "lights up to %.3g deg from the centre, beyond the model's max_light_angle_deg = %.3g: "
            "their obstacle may slide out of the window (raise max_light_angle_deg)",
            beyond,
            max_angle,
        )
    own_npix = jax.eval_shape(lambda m: m(), model).shape[0]
    npix = psf_npix_at_scale(own_npix, float(model.pixel_scale_deg), pixel_scale_deg, max_npix)
    bank = position_psf_bank(model, angles, pixel_scale_deg, npix, batch_size, progress)
    if image.ndim == 2 and bank.ndim == 4:
        raise InputDataError("the image is monochrome (Y) but the model's PSF is RGB")
    return replace_with_billboards(image, lights, bank, psf_index=jnp.arange(valid.size))
