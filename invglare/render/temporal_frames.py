"""Frames of the temporal glare model: its per-frame PSFs convolved with an HDR image.

Step 5 of Ritschel et al. (2009, sec. 5): every frame's spectral PSF
(:class:`~invglare.models.temporal.TemporalGlare`) is convolved with the HDR frame (FFT
convolution, the PSF resampled to the frame's pixel scale when they differ) and
tone-mapped with the operator the model names (`tonemap_name`, `tonemap_params`: gamma
2.2 as in the paper, or any operator of :data:`~invglare.render.tonemap.TONEMAPS`).

:func:`render_sequence` is one `lax.scan` over the dynamics state, so an animation is one
compiled call; a still frame is transformed once per sequence, and what the model
computes once per sequence (:meth:`~invglare.models.temporal.TemporalGlare.sequence_constants`)
is shared by every frame.

```python
run = eqx.filter_jit(lambda m, img, s: render_sequence(m, img, 30, s, 0.05))
state, frames = run(model, scene, model.init_state(10.0))  # (30, H, W, 3) in [0, 1]
```
"""

from __future__ import annotations

import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from invglare._core.checks import as_float
from invglare._core.xla import materialise
from invglare.dynamics import DynamicsState
from invglare.errors import ConfigError, InputDataError
from invglare.models.temporal import (
    TemporalGlare,
    check_n_frames,
    frame_luminance_cd_m2,
    head_motion,
)
from invglare.render.convolve import (
    centre_phase,
    crop_psf_reach,
    linear_period,
    reach_shape,
    resample_psf,
)
from invglare.render.tonemap import tonemap

__all__ = [
    "OUTPUTS",
    "check_display",
    "display",
    "frame_convolver",
    "frame_psf_npix",
    "psf_for_frame",
    "render_frame",
    "render_sequence",
]

#: What :func:`render_sequence` returns per frame: tone-mapped, or linear HDR.
OUTPUTS = ("display", "linear")


def _check_model(model: TemporalGlare) -> None:
    if not model.animated:
        raise ConfigError(
            f"expected an animated model (e.g. a TemporalGlare), got {type(model).__name__}"
        )


def frame_psf_npix(model: TemporalGlare, image_scale_deg: float | None, size: int) -> int | None:
    """Size of the PSF resampled to a frame's scale, or None when no resampling is needed.

    `size` is the frame's larger side (px); the resampled PSF covers the model's field,
    at most ``2 * size + 1`` pixels, and has an odd size (its centre pixel stays centred).
    """
    scale = model.psf_scale_deg
    if image_scale_deg is None or math.isclose(image_scale_deg, scale, rel_tol=1e-6):
        return None
    field_deg = model.propagator.output.npix * scale
    out = min(2 * size + 1, max(3, math.ceil(field_deg / image_scale_deg)))
    return out + 1 - out % 2


def psf_for_frame(
    model: TemporalGlare,
    psf_cf: Float[Array, "c n n"],
    image_scale_deg: float | None,
    size: int,
) -> Float[Array, "c m m"]:
    """A PSF (channels first) at a frame's pixel scale (area-weighted resampling)."""
    out = frame_psf_npix(model, image_scale_deg, size)
    if out is None:
        return psf_cf
    hwc = resample_psf(jnp.moveaxis(psf_cf, 0, -1), model.psf_scale_deg, image_scale_deg, out)
    return jnp.moveaxis(hwc, -1, 0)


def frame_convolver(
    model: TemporalGlare, image: Float[Array, "H W *c"], image_scale_deg: float | None, wrap: bool
) -> tuple[Array, Callable[[Array, Array], Array]]:
    """The image's spectrum, computed once, and a function (spectrum, PSF) -> glare frame.

    The PSF the function takes is channels first, at the model's own scale (as
    :meth:`~invglare.models.temporal.TemporalGlare.psf_cf` gives it). The convolution is
    :func:`invglare.render.convolve.convolve_psf`'s (zero padding to
    :func:`~invglare.render.convolve.linear_period` unless `wrap`), split so that a still
    frame is transformed once per sequence rather than once per frame; the stored spectrum
    includes :func:`~invglare.render.convolve.centre_phase`, so each frame's PSF is only
    padded, not rolled.

    **Raises:** `InputDataError` for a frame of the wrong shape, a monochrome frame with a
    spectral model, or `wrap` with a PSF larger than the frame.
    """
    if image.ndim not in (2, 3):
        raise InputDataError(f"a frame must have shape (H, W) or (H, W, C), got {image.shape}")
    if image.ndim == 2 and model.is_spectral:
        raise InputDataError("a monochrome frame (H, W) needs a monochrome model (one wavelength)")
    height, width = image.shape[:2]
    size = max(height, width)
    n_psf = frame_psf_npix(model, image_scale_deg, size)
    n_psf = model.propagator.output.npix if n_psf is None else n_psf
    if wrap:
        if n_psf > min(height, width):
            raise InputDataError(
                f"wrap = True needs a PSF ({n_psf} px) no larger than the frame "
                f"({height} x {width})"
            )
        p, q = height, width
    else:
        p, q = linear_period(height, n_psf), linear_period(width, n_psf)
    # The PSF as convolved (cropped to its reach unless wrapped) is padded at the grid's
    # corner; the frame's spectrum carries the shift that centres it, once per sequence.
    kept = (n_psf, n_psf) if wrap else reach_shape(height, width, n_psf, n_psf)
    planes = image[None] if image.ndim == 2 else jnp.moveaxis(image, -1, 0)
    spectrum = jnp.fft.rfft2(planes, s=(p, q))
    spectrum = spectrum * jnp.asarray(centre_phase(p, q, *kept), spectrum.dtype)

    def glare(spectrum: Array, psf_cf: Array) -> Array:
        ker = psf_for_frame(model, psf_cf, image_scale_deg, size)
        ker = materialise(ker if wrap else crop_psf_reach(ker, height, width))
        out = jnp.fft.irfft2(spectrum * jnp.fft.rfft2(ker, s=(p, q)), s=(p, q))
        out = out[:, :height, :width]
        return out[0] if image.ndim == 2 else jnp.moveaxis(out, 0, -1)

    return spectrum, glare


def check_display(model: TemporalGlare) -> None:
    """Check the model's tone map (`tonemap_name`, `tonemap_params`) against `TONEMAPS`.

    **Raises:** `ConfigError` naming an unknown tone map (and the valid names) or a
    parameter the operator does not take (and the ones it does).
    """
    _check_model(model)
    try:
        tonemap(jnp.ones((2, 2)), model.tonemap_name, **dict(model.tonemap_params))
    except ConfigError as err:
        raise ConfigError(f"the temporal model's tone map (model.tonemap): {err}") from err


def display(model: TemporalGlare, linear: Float[ArrayLike, "H W *c"]) -> Float[Array, "H W *c"]:
    """Tone-map a linear frame for display (values in [0, 1]) with the model's operator."""
    return tonemap(linear, model.tonemap_name, **dict(model.tonemap_params))


def render_frame(
    model: TemporalGlare,
    image: Float[ArrayLike, "H W *c"],
    state: DynamicsState | None = None,
    image_scale_deg: float | None = None,
    wrap: bool = False,
) -> tuple[Float[Array, "H W *c"], Float[Array, "H W *c"]]:
    """One frame: (linear glare image, tone-mapped display image).

    **Arguments:**

    - `model`: the :class:`~invglare.models.temporal.TemporalGlare` model.
    - `image`: linear HDR frame ``(H, W, 3)`` (or ``(H, W)`` for a mono model), in
      units of ``1 / luminance_scale`` cd/m^2.
    - `state`: the frame's dynamics state (default: at rest, adapted to the frame).
    - `image_scale_deg`: the frame's pixel scale (static float); the PSF is resampled
      to it (area-weighted) when it differs from the model's `pixel_scale_deg`; None:
      the frame is at the PSF's scale.
    - `wrap`: static; circular convolution on the frame's own grid (the light leaving
      one edge re-enters at the opposite one, as in a texture-based GPU pipeline)
      instead of zero padding. Faster (no padded transforms), not exact.

    **Raises:** `ConfigError` for a tone map the render tier does not know,
    `InputDataError` for a frame that does not fit (see :func:`frame_convolver`).
    """
    check_display(model)
    image = as_float(image)
    if state is None:
        state = model.init_state(frame_luminance_cd_m2(image, model.luminance_scale))
    spectrum, glare = frame_convolver(model, image, image_scale_deg, wrap)
    linear = glare(spectrum, model.psf_cf(model.sequence_constants(), state))
    return linear, display(model, linear)


def render_sequence(
    model: TemporalGlare,
    image: Float[ArrayLike, "H W *c"],
    n_frames: int,
    state: DynamicsState | None = None,
    image_scale_deg: float | None = None,
    output: str = "display",
    wrap: bool = False,
    head_acceleration_rad_s2: Float[ArrayLike, "*n 3"] | None = None,
) -> tuple[DynamicsState, Float[Array, "n H W *c"]]:
    """`n_frames` frames of a still HDR image seen through the moving eye (one scan).

    **Arguments:**

    - `model`, `image`, `image_scale_deg`, `wrap`: as for :func:`render_frame`.
    - `n_frames`: number of frames (static int >= 1).
    - `state`: the first frame's state (default: at rest, adapted to the image); pass
      the returned state to continue a sequence in chunks.
    - `output`: ``"display"`` (tone-mapped, [0, 1]) or ``"linear"`` (HDR).
    - `head_acceleration_rad_s2`: the observer's angular acceleration, ``(3,)`` or
      ``(n_frames, 3)`` rad/s^2, which swings the vitreous (default: a still head).

    **Returns:** the state after the last frame, and the frames.

    **Raises:** `ConfigError` for a bad `n_frames` or `output`, or a tone map the render
    tier does not know (with ``output="display"``); `InputDataError` for a frame that
    does not fit.
    """
    _check_model(model)
    check_n_frames(n_frames)
    if output not in OUTPUTS:
        raise ConfigError(f"output = {output!r} is not one of {', '.join(OUTPUTS)}")
    if output == "display":
        check_display(model)
    image = as_float(image)
    lum = frame_luminance_cd_m2(image, model.luminance_scale)
    spectrum, glare = frame_convolver(model, image, image_scale_deg, wrap)
    state = model.init_state(lum) if state is None else state
    constants = model.sequence_constants()
    head = head_motion(head_acceleration_rad_s2, n_frames, lum.dtype)

    def body(s, frame_head):
        linear = glare(spectrum, model.psf_cf(constants, s))
        frame = display(model, linear) if output == "display" else linear
        return model.advance(s, lum, frame_head), frame

    return jax.lax.scan(body, state, head)
