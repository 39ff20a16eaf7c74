"""Batch spectral scaling (sec. 4.3, eq. 14-16, fig. 4 of Scandolo et al.).

In the far field the PSF at ``lambda`` is the reference PSF magnified by ``lambda /
lambda_r`` (eq. 14; :func:`invglare.optics.spectral.scale_psf` keeps the energy per
pixel). A spectral PSF sums many such copies weighted by the colour-matching functions
(eq. 15-16): *full* scaling resamples the reference once per wavelength. *Batch* scaling
samples the wavelengths geometrically, so that their magnifications are ``g^k``: four
consecutive ones, ``g^0 .. g^3`` about the middle, are resampled once into a four-channel
intermediate image, and each further group of four is that image magnified by ``g^(4j)``,
one resampling (one set of interpolation indices and weights) for four samples: "4 + 15"
resamplings for 60 wavelengths. The price is a second interpolation (a little more blur)
and geometric rather than uniform wavelength spacing, denser at the blue end.

The reference wavelength is the geometric mean of the range (529 nm for 400-700 nm), so
the magnifications are symmetric about 1 in the logarithm.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from invglare._core.grids import check_wavelengths_nm
from invglare._core.xla import materialise
from invglare.errors import ConfigError
from invglare.optics.spectral import (
    _axis_interpolation,  # the interpolation of scale_psf
    scale_psf,
    scaled_copies,
    spectral_weights,
)

BATCH = 4


def reference_wavelength_nm(lo_nm: float, hi_nm: float) -> float:
    """The paper's reference: the geometric mean of the range."""
    return math.sqrt(lo_nm * hi_nm)


def batch_wavelengths_nm(lo_nm: float, hi_nm: float, n: int) -> np.ndarray:
    """`n` wavelengths from `lo_nm` to `hi_nm`, geometrically spaced (n a multiple of 4)."""
    check_wavelengths_nm([lo_nm, hi_nm])
    if isinstance(n, bool) or not isinstance(n, int) or n < BATCH or n % BATCH:
        raise ConfigError(f"batch spectral scaling takes a multiple of {BATCH} samples, got {n!r}")
    if not hi_nm > lo_nm:
        raise ConfigError(f"the wavelength range must increase, got {lo_nm:g} to {hi_nm:g} nm")
    return lo_nm * (hi_nm / lo_nm) ** (np.arange(n) / (n - 1))


class BatchPlan:
    """Magnifications of the intermediate channels and of the batches, and the weights.

    `inner` (4,), `outer` (n / 4,), `weights` ``(n / 4, 4, c)``: wavelength ``4 j + i`` has
    magnification ``outer[j] * inner[i]`` and weights ``weights[j, i]``.
    """

    def __init__(self, wavelengths_nm: np.ndarray, reference_nm: float, weights: np.ndarray):
        mags = np.asarray(wavelengths_nm, float) / reference_nm
        n = mags.size
        ratio = mags[1] / mags[0]
        if not np.allclose(mags[1:] / mags[:-1], ratio, rtol=1e-9):
            raise ConfigError("batch spectral scaling needs geometrically spaced wavelengths")
        mid = (n // BATCH - 1) // 2  # the batch whose outer magnification is nearest 1
        self.inner = mags[mid * BATCH : (mid + 1) * BATCH]
        self.outer = mags[::BATCH] / mags[mid * BATCH]
        self.weights = np.asarray(weights, float).reshape(n // BATCH, BATCH, -1)
        self.wavelengths_nm = np.asarray(wavelengths_nm, float)

    @classmethod
    def build(cls, lo_nm: float, hi_nm: float, n: int, illuminant: str = "E") -> BatchPlan:
        """Geometric samples over a range, the paper's reference and XYZ weights."""
        wl = batch_wavelengths_nm(lo_nm, hi_nm, n)
        return cls(wl, reference_wavelength_nm(lo_nm, hi_nm), spectral_weights(wl, illuminant))


def _magnify_texels(image: Float[Array, "h w k"], factor: Array) -> Float[Array, "w h k"]:
    """`scale_psf` of a ``k``-channel image kept channels last, like the paper's RGBA
    texels: each interpolation tap reads ``k`` contiguous values. Returns it transposed
    (rows and columns swapped), the order its two passes leave."""
    h, w = image.shape[:2]
    r0, r1, rw0, rw1 = _axis_interpolation(h, factor)
    c0, c1, cw0, cw1 = _axis_interpolation(w, factor)
    rows = image[r0] * rw0[:, None, None] + image[r1] * rw1[:, None, None]
    rows_t = materialise(jnp.swapaxes(rows, 0, 1))
    return rows_t[c0] * cw0[:, None, None] + rows_t[c1] * cw1[:, None, None]


def batch_scaled_copies(psf_ref: Float[Array, "h w"], plan: BatchPlan) -> Float[Array, "c h w"]:
    """``sum_k weights[k] * psf(lambda_k)`` by batch scaling (channels first).

    Four resamplings make the four-channel intermediate image (channels last), then one
    four-channel resampling per batch (a `lax.scan`), contracted with its ``(4, c)``
    weights.
    """
    dtype = psf_ref.dtype
    texels = jnp.stack([scale_psf(psf_ref, float(m)) for m in plan.inner], axis=-1)
    weights = jnp.asarray(plan.weights, dtype)
    c = weights.shape[-1]

    def add_batch(acc, sample):
        magnification, w = sample
        copies_t = _magnify_texels(texels, magnification)  # (w, h, 4): four samples
        # The (4, c) contraction written out: as a matrix product XLA took 4 times longer.
        return acc + sum(copies_t[..., i : i + 1] * w[i] for i in range(BATCH)), None

    zero = jnp.zeros((psf_ref.shape[1], psf_ref.shape[0], c), dtype)
    total_t, _ = jax.lax.scan(add_batch, zero, (jnp.asarray(plan.outer, dtype), weights))
    return jnp.transpose(total_t, (2, 1, 0))


def full_scaled_copies(psf_ref: Float[Array, "h w"], plan: BatchPlan) -> Float[Array, "c h w"]:
    """The same sum with one resampling per wavelength (the paper's "full" scaling)."""
    mags = plan.outer[:, None] * plan.inner[None, :]
    weights = plan.weights.reshape(-1, plan.weights.shape[-1])
    return scaled_copies(
        psf_ref, jnp.asarray(mags.reshape(-1), psf_ref.dtype), jnp.asarray(weights, psf_ref.dtype)
    )
