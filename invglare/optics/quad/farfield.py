"""Far field of a quad layout (Fraunhofer): any output sampling, the FFT/MFT normalisation.

The quads are the raster read as what it is, a piecewise-constant function (each pixel a
box of the pitch): its continuous Fourier transform has no period, so the far field has no
aliasing and needs no padding at any pixel scale or field. Against the matrix Fourier
transform of the same raster (the DFT of its samples) it differs by exactly the pixel's own
transfer function, ``sinc(f_x p) sinc(f_y p)``.

**Normalisation** (:mod:`invglare.optics.fraunhofer`): per output pixel, the fraction of the
transmitted power landing there,

    psf = |F(theta / lambda)|^2 (dtheta / lambda)^2 / (sum |t|^2 pitch^2),

which in raster pixels and cycles per pixel is ``|F_px|^2 step^2 / sum |t|^2`` with
``step = dtheta * pitch / lambda``, the output pixel in cycles per raster pixel.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from invglare.optics.quad.plan import QuadPlan
from invglare.optics.quad.transform import (
    Tiles,
    box_kernel,
    far_field_quadrants,
    parity_terms,
    quadrant_index,
    unfold,
)

# Guards the normalisation of a layout that transmits nothing.
_TINY_POWER = 1e-30


def plan_amplitudes(
    plan: QuadPlan, raster: Float[Array, "n n"]
) -> tuple[Float[Array, " k"], Float[Array, ""]]:
    """The quads' signed intensities read from `raster` (in the plan's order) and the
    power ``sum |f|^2`` of what they represent."""
    levels = plan.layout.intensities(raster)
    amps = plan.layout.amplitudes(levels)[jnp.asarray(plan.order)]
    return amps, plan.layout.power(levels)


def far_field_terms(
    plan: QuadPlan,
    amplitudes: Float[Array, " k"],
    step_px: Float[ArrayLike, ""],
    npix: int,
    tiles: Tiles | None = None,
) -> tuple[Array, Array, Array, Array]:
    """The parity terms (px^2) on the quadrant of an `npix` output of pixel `step_px`,
    only on `tiles` when given (:func:`~invglare.optics.quad.cull.cull_tiles`)."""
    step = jnp.asarray(step_px, amplitudes.dtype)
    index = quadrant_index(npix)
    return parity_terms(plan, box_kernel, amplitudes, step, index, index, tiles=tiles)


def far_field_from_terms(
    terms: tuple[Array, Array, Array, Array],
    power: Float[ArrayLike, ""],
    step_px: Float[ArrayLike, ""],
    npix: int,
) -> Float[Array, "npix npix"]:
    """The unit-energy PSF from parity terms and the raster's power ``sum |t|^2``."""
    same, opposite = far_field_quadrants(terms)
    scale = jnp.asarray(step_px, same.dtype) ** 2 / jnp.maximum(power, _TINY_POWER)
    return unfold(npix, same * scale, opposite * scale)


def quad_far_field(
    plan: QuadPlan,
    raster: Float[Array, "n n"],
    step_px: Float[ArrayLike, ""],
    npix: int,
    tiles: Tiles | None = None,
) -> Float[Array, "npix npix"]:
    """Unit-energy far-field PSF of the raster's quads on an ``npix`` output grid.

    **Arguments:**

    - `plan`: from :func:`~invglare.optics.quad.plan.make_plan`.
    - `raster`: the transmission the quads read their intensities from (traced or not).
    - `step_px`: output pixel in cycles per raster pixel, ``dtheta * pitch / lambda``.
    - `npix`: output size; pixel ``npix // 2`` is the axis.
    - `tiles`: the output tiles culling keeps (None: all).

    **Returns:** the PSF (fraction of the transmitted power per pixel).
    """
    amps, power = plan_amplitudes(plan, raster)
    terms = far_field_terms(plan, amps, step_px, npix, tiles)
    return far_field_from_terms(terms, power, step_px, npix)
