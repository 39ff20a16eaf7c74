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
so ``E`` is tabulated once per distinct edge and output frequency (the paper's 1-D table,
first pass, per axis), and the quads are combined by the matrix products of
:mod:`.transform` (second pass). As each interval's ``g`` is a difference of two table
rows, a quad is four signed corner terms, and the products run over the distinct edges
(:func:`corner_plan`): at most one per pixel boundary, where the distinct intervals of
quads of many sizes are more (the whirl at 1024 px: 503 and 511 edges up to sign, 1 285
intervals; its near field 117 -> 38 ms). Mirror symmetries of the aperture are used as in
the far field (there is no Hermitian symmetry here: the chirp is complex).

**The lattice table.** With ``r = step / alpha`` (the output pixel at the distance over the
raster pitch, ``dtheta d / pitch``; the same at every wavelength) the table's arguments are
``s = sqrt(2 alpha) (e - k r)`` for edges ``e`` (multiples of half a pixel) and output
indices ``k``. When ``r`` is a fraction ``p / q`` with a small ``q`` (the raster observed on
its own grid: ``r = 1``), ``e - k r`` takes few distinct values, each shared by a diagonal of
the table: ``E`` is evaluated once per value (about 1 500 instead of 520 000 at 1024 px, the
Fresnel integrals being a third of the near field's time there) and spread by a gather.
:class:`QuadFresnel <invglare.optics.propagator.QuadFresnel>` finds ``r`` when it is
prepared. The value is exact only at that ``r`` (up to the float rounding of computing
``r``): a call at another one (a fitted distance that has moved) evaluates the whole table
instead, and the derivative is always the whole table's, ``dE/ds = exp(i pi s^2 / 2)`` per
entry.

The near field has the far field's normalisation: ``|U|^2 (dtheta / lambda)^2`` per pixel
over the power through the aperture (the whole plane holds the represented raster's
``sum |t|^2 / sum |t|`` of it, as for the far field).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import fresnel
from jaxtyping import Array, ArrayLike, Complex, Float

from invglare._core.xla import materialise
from invglare.optics.quad.farfield import _TINY_POWER, plan_amplitudes
from invglare.optics.quad.plan import QuadPlan
from invglare.optics.quad.transform import FreqAxis, Tiles, quadrant_terms, unfold


def fresnel_e(s: Float[Array, "*shape"]) -> Complex[Array, "*shape"]:
    """``E(s) = C(s) + i S(s)``, the Fresnel integrals ``int_0^s exp(i pi t^2 / 2) dt``."""
    s_int, c_int = fresnel(s)
    return c_int + 1j * s_int


#: The lattice table's value is used at a ratio ``r`` within this many float roundings
#: (units in the last place) of the one it was built for: ``r`` computed in float32 from
#: the grid's pixel and the distance is no closer, and the whole table's own arguments carry
#: the same rounding. Farther (a moved distance, a finite difference in float64), the whole
#: table is evaluated.
LATTICE_ULPS = 8
#: Denominators ``q`` of the ratios ``p / q`` the lattice table recognises.
LATTICE_DENOMINATORS = tuple(range(1, 9))
#: The lattice table is used when it needs at most this fraction of the whole table's
#: Fresnel evaluations.
_LATTICE_WORTH = 0.25


def lattice_ratio(ratio: float) -> float | None:
    """`ratio` as a fraction ``p / q`` (``q`` in :data:`LATTICE_DENOMINATORS`) when it is one
    within 1e-6 relative (the float32 rounding of the grid's pixel and distance), else None."""
    if not (math.isfinite(ratio) and ratio > 0):
        return None
    for q in LATTICE_DENOMINATORS:
        p = round(ratio * q)
        if p > 0 and abs(ratio * q - p) <= 1e-6 * ratio * q:
            return p / q
    return None


@dataclasses.dataclass(frozen=True)
class LatticeFresnelKernel:
    """:func:`fresnel_edge_kernel` for an output whose ``step / alpha`` is `ratio` (static,
    from :func:`lattice_ratio`): the Fresnel integrals by the lattice table."""

    ratio: float

    def __call__(self, centre_px, width_px, axis: FreqAxis, alpha):
        return fresnel_edge_kernel(centre_px, width_px, axis, alpha, self.ratio)


def _lattice_table(edges: np.ndarray, index: np.ndarray, ratio: float):
    """The Fresnel table ``E(root (e - k r))`` as a function of ``(root, r)``, evaluated once
    per distinct ``e - k ratio`` while ``r`` is `ratio` (None where that saves little)."""
    shift = edges[:, None] - index[None, :] * ratio
    values, inverse = np.unique(np.round(shift, 9), return_inverse=True)
    if values.size > _LATTICE_WORTH * shift.size:
        return None
    inverse = inverse.reshape(shift.shape)

    def shifts(r):
        """``(e - k r, k)`` over the whole table."""
        k = jnp.asarray(index, r.dtype)[None, :]
        return jnp.asarray(edges, r.dtype)[:, None] - k * r, k

    @jax.custom_jvp
    def table(root, r):
        def lattice(root, r):
            return fresnel_e(root * jnp.asarray(values, r.dtype))[inverse]

        def dense(root, r):
            return fresnel_e(root * shifts(r)[0])

        own = jnp.abs(r - ratio) <= LATTICE_ULPS * jnp.finfo(r.dtype).eps * ratio
        return jax.lax.cond(own, lattice, dense, root, r)

    @table.defjvp
    def _table_jvp(primals, tangents):
        root, r = primals
        d_root, d_r = tangents
        shift, k = shifts(r)
        s = root * shift
        ds = d_root * shift - root * k * d_r
        phase = (0.5 * math.pi) * s * s
        return table(root, r), jax.lax.complex(jnp.cos(phase), jnp.sin(phase)) * ds

    return table


def _fresnel_table(edges, axis: FreqAxis, alpha, ratio: float | None):
    """``E(sqrt(2 alpha) (e - f / alpha))`` for edges `e` (rows; numpy where `ratio` is
    given) and the frequencies of `axis` (columns), by the lattice table where `ratio`
    allows it, and ``sqrt(2 alpha)``."""
    dtype = axis.step.dtype
    root = jnp.sqrt(2.0 * alpha)
    lattice = None
    if ratio is not None and axis.offset is None:
        lattice = _lattice_table(np.asarray(edges), np.asarray(axis.index, np.float64), ratio)
    if lattice is not None:
        table = lattice(root, axis.step / alpha)
    else:
        freq = axis.freq(dtype)
        table = fresnel_e(root * (jnp.asarray(edges, dtype)[:, None] - freq[None, :] / alpha))
    # The table is put in memory: fused into each of its readers (real and imaginary parts,
    # the sum of Gauss's product), XLA's CPU gathers ran per element (the near field at
    # 1024 px: circle 52 -> 38 ms, whirl 127 -> 113 ms).
    return materialise(table), root


def fresnel_kernel(
    centre_px, width_px, axis: FreqAxis, alpha: Float[Array, ""]
) -> tuple[Complex[Array, "n m"], Complex[Array, "n m"]]:
    """Near-field axis kernel: the parts of ``g`` even and odd in the interval's centre.

    ``g(f; c)`` over ``[c - w/2, c + w/2]`` without the common phase; ``g(f; -c) = g(-f;
    c)``, so the even part is ``(g(f; c) + g(-f; c)) / 2`` and the odd part the difference.
    Both come from one table of ``E`` at the distinct edges ``+-(c +- w/2)`` (intervals
    given as traced arrays: one row per edge). The near field of a static plan sums
    corners (:func:`fresnel_edge_kernel`) instead; this kernel serves the traced plans of
    progressive frames, culling's coarse pass and the tests' reference.
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
    table, root = _fresnel_table(edges, axis, alpha, None)
    scale = 1.0 / root
    plus = (table[where[1]] - table[where[0]]) * scale  # g(f; c)
    minus = (table[where[3]] - table[where[2]]) * scale  # g(f; -c) = g(-f; c)
    return materialise(0.5 * (plus + minus)), materialise(0.5 * (plus - minus))


def fresnel_edge_kernel(
    centre_px: np.ndarray,
    width_px: np.ndarray,
    axis: FreqAxis,
    alpha: Float[Array, ""],
    ratio: float | None = None,
) -> tuple[Complex[Array, "n m"], Complex[Array, "n m"]]:
    """The axis kernel of a corner plan (:func:`corner_plan`): at each edge ``e`` (its
    `centre_px`, > 0; `width_px` is not used), ``h(f; e) = sgn(e) E(sqrt(2 alpha) (e - f /
    alpha)) / sqrt(2 alpha)``, split into its parts even and odd in ``e`` as
    :func:`fresnel_kernel` splits ``g`` (``h(f; -e) = h(-f; e)``, as ``E`` is odd).
    `ratio`: ``step / alpha`` where the lattice table may be used (see the module's
    docstring; None: the whole table)."""
    edges = np.asarray(centre_px, np.float64)
    table, root = _fresnel_table(np.concatenate([edges, -edges]), axis, alpha, ratio)
    n = edges.size
    pos, neg = table[:n], table[n:]
    half_scale = 0.5 / root
    return materialise((pos - neg) * half_scale), materialise((pos + neg) * half_scale)


@functools.lru_cache(maxsize=32)
def corner_plan(plan: QuadPlan) -> tuple[QuadPlan, np.ndarray, np.ndarray]:
    """`plan`'s quads as their corners, for the near field's edge kernel.

    A quad's interval kernel is a difference of the Fresnel table at its two edges (``g =
    (E(s_hi) - E(s_lo)) / sqrt(2 alpha)``), so a quad of amplitude ``a`` is four corner
    terms ``+-a E(y edge) E(x edge)``: the near field is a sum over the corners of
    :func:`fresnel_edge_kernel` products. The corners' rows and columns are the distinct
    edges up to sign, at most 513 for a 1024 px raster (the whirl: 503 rows, where its
    quads have 1 285 distinct row intervals), and the corner matrix is small enough to be
    dense (the plan's `dense_inner`): the two products that make the near field shrink by
    that factor and the per-quad gathers go.

    **Returns:** the corner plan (the plan's mirrors: a mirror-symmetric raster has
    corners even in the edge once their amplitudes carry ``sgn(e)``, as the kernel does),
    and for each corner entry the index of its quad in `plan`'s order and its factor (the
    corner's sign times the signs of its two edges): the entries' amplitudes are
    ``amplitudes[source] * factor``.
    """
    k = plan.quad_row.size
    cy = plan.sign_y * plan.row_c[plan.quad_row]
    cx = plan.sign_x * plan.col_c[plan.quad_col]
    hy, hx = plan.row_s[plan.quad_row] / 2.0, plan.col_s[plan.quad_col] / 2.0
    # Corners (hi, hi), (lo, lo) with +, (hi, lo), (lo, hi) with -.
    ey = np.concatenate([cy + hy, cy - hy, cy + hy, cy - hy])
    ex = np.concatenate([cx + hx, cx - hx, cx - hx, cx + hx])
    corner_sign = np.repeat([1.0, 1.0, -1.0, -1.0], k)
    if np.any(ey == 0) or np.any(ex == 0):
        raise ValueError("quad edges must lie on pixel boundaries (half-integers about the origin)")
    row_c, quad_row = np.unique(np.abs(ey), return_inverse=True)
    col_c, quad_col = np.unique(np.abs(ex), return_inverse=True)
    order = np.argsort(quad_row, kind="stable")
    source = np.tile(np.arange(k), 4)[order]
    corners = QuadPlan(
        layout=plan.layout,
        mirror_x=plan.mirror_x,
        mirror_y=plan.mirror_y,
        row_c=row_c,
        row_s=np.zeros_like(row_c),
        col_c=col_c,
        col_s=np.zeros_like(col_c),
        quad_row=quad_row[order],
        quad_col=quad_col[order],
        sign_y=np.sign(ey)[order],
        sign_x=np.sign(ex)[order],
        order=plan.order[source],
        dense_inner=True,
    )
    return corners, source, (corner_sign * np.sign(ey) * np.sign(ex))[order]


def near_field_terms(
    plan: QuadPlan,
    amplitudes: Float[Array, " k"],
    step_px: Float[ArrayLike, ""],
    alpha: Float[ArrayLike, ""],
    npix: int,
    tiles: Tiles | None = None,
    ratio: float | None = None,
) -> tuple[Array, Array, Array, Array]:
    """The near-field parity terms (complex, px^2; see :func:`~.transform.quadrant_terms`),
    evaluated over the plan's corners (:func:`corner_plan`); `ratio` as for
    :func:`fresnel_edge_kernel`."""
    corners, source, factor = corner_plan(plan)
    amps = amplitudes[jnp.asarray(source)] * jnp.asarray(factor, amplitudes.dtype)
    kernel = fresnel_edge_kernel if ratio is None else LatticeFresnelKernel(ratio)
    return quadrant_terms(corners, kernel, amps, step_px, npix, alpha, tiles)


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
    ratio: float | None = None,
) -> Float[Array, "npix npix"]:
    """Fresnel PSF of the raster's quads on an ``npix`` output grid, per unit power.

    The arguments are those of :func:`~invglare.optics.quad.farfield.quad_far_field`, and
    `alpha`, the chirp in raster pixels, ``pitch^2 / (lambda d)`` (``4 N_F / D_px^2`` for
    a Fresnel number ``N_F`` of an aperture ``D_px`` pixels across); `ratio`, where given,
    ``step_px / alpha`` as a static fraction (:func:`lattice_ratio`), for the lattice table.

    **Returns:** the PSF (fraction of the power through the aperture per pixel), indexed
    by the angle ``theta = x' / d`` of the observation point ``x'``.
    """
    amps, power = plan_amplitudes(plan, raster)
    terms = near_field_terms(plan, amps, step_px, alpha, npix, tiles, ratio)
    return near_field_from_terms(terms, power if power_px is None else power_px, step_px, npix)
