"""Colour constants shared by every tier."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

#: Rec. 709 / sRGB luminance weights of linear R, G, B (the default colourspace's Y).
REC709_Y = (0.2126, 0.7152, 0.0722)


def rec709_luminance(rgb: Float[ArrayLike, "*shape 3"]) -> Float[Array, "*shape"]:
    """Luminance Y of linear Rec. 709 / sRGB values, channels last (JAX)."""
    rgb = jnp.asarray(rgb)
    return rgb @ jnp.asarray(REC709_Y, dtype=rgb.dtype)


def rec709_luminance_np(rgb: Float[ArrayLike, "*shape 3"]) -> np.ndarray:
    """:func:`rec709_luminance` in numpy (for files and reports, off the JAX path)."""
    rgb = np.asarray(rgb)
    return rgb @ np.asarray(REC709_Y, dtype=rgb.dtype if rgb.dtype.kind == "f" else float)
