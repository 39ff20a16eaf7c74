"""Near field of a quad layout: Fresnel diffraction in closed form (sec. 4.5, eq. 17-23).

The Fresnel field at distance ``d`` (eq. 4 of Scandolo et al.; eq. 3 of the temporal-glare
paper, which :class:`~invglare.optics.propagator.FresnelMFT` samples) is the Fourier
transform of the aperture times the chirp ``exp(i pi r^2 / (lambda d))``, read at
``f = theta / lambda``. Over one quad it separates (eq. 18) into two integrals of the form

    g(f) = int_a^b exp(i pi alpha x^2) exp(-2 pi i f x) dx
         = exp(-i pi f^2 / alpha) sqrt(1 / (2 alpha)) [E(s_b) - E(s_a)],

``s = sqrt(2 alpha) (x - f / alpha)``, ``E = C + i S`` the Fresnel integrals (appendix A:
completing the square) and ``alpha = pitch^2 / (lambda d)`` in raster pixels. The phase in
front is the same for every quad and drops out of the intensity. Nothing is sampled: no
chirp to resolve, no padding, no aliasing however short the distance (the discrete
transforms need the chirp under Nyquist, which :func:`~invglare.optics.propagator.
make_propagator` enforces for them).

**Two passes** (the paper's separable evaluation): every interval edge is a pixel boundary,
so ``E`` is tabulated once per distinct edge and output frequency (the paper's 1-D table),
each interval's ``g`` is a difference of two table rows (first pass, per axis), and the
quads are combined by the matrix products of :mod:`.transform` (second pass). Mirror
symmetries of the aperture are used as in the far field (there is no Hermitian symmetry
here: the chirp is complex).

The near field has the far field's normalisation: ``|U|^2 (dtheta / lambda)^2`` per pixel
over the power through the aperture (the whole plane holds the represented raster's
``sum |t|^2 / sum |t|`` of it, as for the far field).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jax.scipy.special import fresnel
from jaxtyping import Array, ArrayLike, Complex, Float

from invglare.optics.quad.farfield import _TINY_POWER, plan_amplitudes
from invglare.optics.quad.plan import QuadPlan
from invglare.optics.quad.transform import FreqAxis, Tiles, quadrant_terms, unfold


def fresnel_e(s: Float[Array, "*shape"]) -> Complex[Array, "*shape"]:
    """``E(s) = C(s) + i S(s)``, the Fresnel integrals ``int_0^s exp(i pi t^2 / 2) dt``."""
    s_int, c_int = fresnel(s)
    return c_int + 1j * s_int


def fresnel_kernel(
    centre_px, width_px, axis: FreqAxis, alpha: Float[Array, ""]
) -> tuple[Complex[Array, "n m"], Complex[Array, "n m"]]:
    """Near-field axis kernel: the parts of ``g`` even and odd in the interval's centre.

    ``g(f; c)`` over ``[c - w/2, c + w/2]`` without the common phase; ``g(f; -c) = g(-f;
    c)``, so the even part is ``(g(f; c) + g(-f; c)) / 2`` and the odd part the difference.
    Both come from one table of ``E`` at the distinct edges ``+-(c +- w/2)`` (intervals
    given as traced arrays: one row per edge).
    """
    dtype = axis.step.dtype
    if isinstance(centre_px, np.ndarray):
        lo, hi = centre_px - width_px / 2.0, centre_px + width_px / 2.0
        edges, where = np.unique(np.concatenate([lo, hi, -hi, -lo]), return_inverse=True)
        where = where.reshape(4, -1)
    else:
        c, w = jnp.asarray(centre_px, dtype), jnp.asarray(width_px, dtype)
        edges = jnp.concatenate([c - w / 2.0, c + w / 2.0, -c - w / 2.0, -c + w / 2.0])
        where = np.arange(edges.shape[0]).reshape(4, -1)
    root = jnp.sqrt(2.0 * alpha)
    freq = axis.freq(dtype)
    s = root * (jnp.asarray(edges, dtype)[:, None] - freq[None, :] / alpha)
    table = fresnel_e(s)
    scale = 1.0 / root
    plus = (table[where[1]] - table[where[0]]) * scale  # g(f; c)
    minus = (table[where[3]] - table[where[2]]) * scale  # g(f; -c) = g(-f; c)
    return 0.5 * (plus + minus), 0.5 * (plus - minus)


def near_field_terms(
    plan: QuadPlan,
    amplitudes: Float[Array, " k"],
    step_px: Float[ArrayLike, ""],
    alpha: Float[ArrayLike, ""],
    npix: int,
    tiles: Tiles | None = None,
) -> tuple[Array, Array, Array, Array]:
    """The near-field parity terms (complex, px^2; see :func:`~.transform.quadrant_terms`)."""
    return quadrant_terms(plan, fresnel_kernel, amplitudes, step_px, npix, alpha, tiles)


def near_field_from_terms(
    terms: tuple[Array, Array, Array, Array],
    power: Float[ArrayLike, ""],
    step_px: Float[ArrayLike, ""],
    npix: int,
) -> Float[Array, "npix npix"]:
    """The PSF from the near-field parity terms and the power through the aperture
    (aperture pixels)."""
    t1, t2, t3, t4 = terms

    def power_of(sx, sy):
        u = t1 + sx * t2 + sy * t3 + (sx * sy) * t4
        return u.real**2 + u.imag**2

    scale = jnp.asarray(step_px, t1.real.dtype) ** 2 / jnp.maximum(power, _TINY_POWER)
    quadrants = [power_of(sx, sy) * scale for sy, sx in ((1, 1), (1, -1), (-1, 1), (-1, -1))]
    return unfold(npix, *quadrants)


def quad_near_field(
    plan: QuadPlan,
    raster: Float[Array, "n n"],
    step_px: Float[ArrayLike, ""],
    alpha: Float[ArrayLike, ""],
    npix: int,
    tiles: Tiles | None = None,
    power_px: Float[ArrayLike, ""] | None = None,
) -> Float[Array, "npix npix"]:
    """Fresnel PSF of the raster's quads on an ``npix`` output grid, per unit power.

    The arguments are those of :func:`~invglare.optics.quad.farfield.quad_far_field`, and
    `alpha`, the chirp in raster pixels, ``pitch^2 / (lambda d)`` (``4 N_F / D_px^2`` for
    a Fresnel number ``N_F`` of an aperture ``D_px`` pixels across).

    **Returns:** the PSF (fraction of the power through the aperture per pixel), indexed
    by the angle ``theta = x' / d`` of the observation point ``x'``.
    """
    amps, power = plan_amplitudes(plan, raster)
    terms = near_field_terms(plan, amps, step_px, alpha, npix, tiles)
    return near_field_from_terms(terms, power if power_px is None else power_px, step_px, npix)
