"""Far field of a quad layout (Fraunhofer): any output sampling, the FFT/MFT normalisation.

The quads are the raster read as what it is, a piecewise-constant function (each pixel a
box of the pitch): its continuous Fourier transform has no period, so the far field has no
aliasing and needs no padding at any pixel scale or field. Against the matrix Fourier
transform of the same raster (the DFT of its samples) it differs by exactly the pixel's own
transfer function, ``sinc(f_x p) sinc(f_y p)``.

**Normalisation** (:mod:`invglare.optics.fraunhofer`): per output pixel, the fraction of the
power through the aperture landing there,

    psf = |F(theta / lambda)|^2 (dtheta / lambda)^2 / P,

which in raster pixels and cycles per pixel is ``|F_px|^2 step^2 / (P / pitch^2)`` with
``step = dtheta * pitch / lambda``, the output pixel in cycles per raster pixel. ``P`` is
the aperture's area in closed form where the caller passes it (`power_px`), else the
represented raster's transmission ``sum |t| pitch^2``: as for the FFT and MFT, the PSF of a
sharp-edged aperture then sums to a little under 1 over the whole plane (the raster's
``sum |t|^2 / sum |t|``), and its Airy core matches the closed form.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from invglare.optics.quad.plan import QuadPlan
from invglare.optics.quad.transform import (
    Tiles,
    box_kernel,
    far_field_quadrants,
    quadrant_terms,
    unfold,
)

# Guards the normalisation of a layout that transmits nothing.
_TINY_POWER = 1e-30


def plan_amplitudes(
    plan: QuadPlan, raster: Float[Array, "n n"]
) -> tuple[Float[Array, " k"], Float[Array, ""]]:
    """The quads' signed intensities read from `raster` (in the plan's order) and the
    power through what they represent, ``sum |f|`` (aperture pixels)."""
    levels = plan.layout.intensities(raster)
    amps = plan.layout.amplitudes(levels)[jnp.asarray(plan.order)]
    return amps, plan.layout.transmission(levels)


def far_field_terms(
    plan: QuadPlan,
    amplitudes: Float[Array, " k"],
    step_px: Float[ArrayLike, ""],
    npix: int,
    tiles: Tiles | None = None,
) -> tuple[Array, Array, Array, Array]:
    """The far-field parity terms (px^2; see :func:`~.transform.quadrant_terms`)."""
    return quadrant_terms(plan, box_kernel, amplitudes, step_px, npix, tiles=tiles)


def far_field_from_terms(
    terms: tuple[Array, Array, Array, Array],
    power: Float[ArrayLike, ""],
    step_px: Float[ArrayLike, ""],
    npix: int,
) -> Float[Array, "npix npix"]:
    """The PSF from parity terms and the power through the aperture (aperture pixels)."""
    same, opposite = far_field_quadrants(terms)
    scale = jnp.asarray(step_px, same.dtype) ** 2 / jnp.maximum(power, _TINY_POWER)
    return unfold(npix, same * scale, opposite * scale)


def quad_far_field(
    plan: QuadPlan,
    raster: Float[Array, "n n"],
    step_px: Float[ArrayLike, ""],
    npix: int,
    tiles: Tiles | None = None,
    power_px: Float[ArrayLike, ""] | None = None,
) -> Float[Array, "npix npix"]:
    """Far-field PSF of the raster's quads on an ``npix`` output grid, per unit power.

    **Arguments:**

    - `plan`: from :func:`~invglare.optics.quad.plan.make_plan`.
    - `raster`: the transmission the quads read their intensities from (traced or not).
    - `step_px`: output pixel in cycles per raster pixel, ``dtheta * pitch / lambda``.
    - `npix`: output size; pixel ``npix // 2`` is the axis.
    - `tiles`: the output tiles culling keeps (None: all).
    - `power_px`: the power through the aperture in aperture pixels (a closed-form area
      over ``pitch^2``); None: the represented raster's transmission ``sum |t|``.

    **Returns:** the PSF (fraction of the power through the aperture per pixel).
    """
    amps, power = plan_amplitudes(plan, raster)
    terms = far_field_terms(plan, amps, step_px, npix, tiles)
    return far_field_from_terms(terms, power if power_px is None else power_px, step_px, npix)
