"""Closed-form transforms of quads (eq. 10-13 of Scandolo et al.), evaluated as matrix products.

A quad of width ``w`` centred at ``c`` (one axis) transforms to ``w sinc(f w) exp(-2 pi i f c)``
(eq. 11), a quad to the product of its two axes (eq. 12), a quad list to the sum (eq. 8).
Every quad's x factor depends only on its column interval, its y factor only on its row
interval, so with the distinct intervals as rows and columns of a sparse amplitude matrix
``P``, the transform is ``K_y^T P K_x``: one gather-and-sum over the quads and one dense
matrix product over the distinct rows. The shift property (eq. 13: equal quads share their
sinc envelope, each adds a phase) is the statement that the envelope is a factor of a
kernel column.

**Parity split.** Each axis kernel is split into its parts even and odd in the interval's
centre, ``w sinc(f w) cos(2 pi f c)`` and ``w sinc(f w) sin(2 pi f c)``: intervals at
``+c`` and ``-c`` then share one row (the odd part carries the sign), and each part is
even or odd in ``f``. With ``T_1 .. T_4`` the four products (even-even, even-odd, odd-even,
odd-odd, y first) evaluated on the quadrant ``f_x, f_y >= 0``, the transform at
``(sx f_x, sy f_y)`` for any signs is

    F = T_1 - i sx T_2 - i sy T_3 - sx sy T_4,

so the whole plane comes from quadrant-sized real products, with no assumption on the
aperture (sec. 4.3's symmetry, made exact). An aperture symmetric about an axis has no
odd part along it: its terms vanish and are skipped (:class:`~.plan.QuadPlan` records the
mirrors), which halves the work per mirror. The near field (:mod:`.nearfield`) has the
same structure with complex kernels. Skipping is an acceleration of the value only: the
derivative is always that of all four terms (a custom JVP), so a fitted parameter that
breaks the symmetry (a rotation) still gets its exact gradient.

All lengths here are in raster pixels and frequencies in cycles per pixel; the callers
convert (``f_px = theta * pitch / lambda``).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from invglare._core.xla import materialise
from invglare.optics.quad.plan import QuadPlan

#: Below ``|pi x|`` of this the sinc is its Taylor series (both it and its derivative exact).
_SINC_SERIES_BELOW = 1.0
#: Terms of that series: ``(pi x)^(2k) / (2k + 1)!`` for k = 1 .. 9 (error < 1e-17 below 1).
_SINC_TERMS = 9


class FreqAxis(NamedTuple):
    """Frequencies ``index * step + offset`` (cycles/px) along one axis of the output.

    `index` is a static integer numpy array (>= 0); `step` and `offset` are scalars that
    may be traced (`offset` None for 0).
    """

    index: np.ndarray
    step: Array
    offset: Array | None = None

    def freq(self, dtype) -> Array:
        f = jnp.asarray(self.index, dtype) * self.step
        return f if self.offset is None else f + self.offset


#: An axis kernel: ``kernel(centre_px, width_px, axis, params) -> (even, odd)``, each of shape
#: ``(intervals, len(axis.index))``, for intervals given as numpy arrays (px).
Kernel = Callable[[np.ndarray, np.ndarray, FreqAxis, object], tuple[Array, Array]]


def sinc(x: Float[ArrayLike, "*shape"]) -> Float[Array, "*shape"]:
    """``sin(pi x) / (pi x)``, 1 at 0, with value and derivative exact near 0.

    Below ``|pi x| = 1`` it is the Taylor series (Horner form): ``jnp.sinc`` divides there,
    and its derivative, ``(cos y - sin y / y) / x``, loses its digits to cancellation as
    ``x -> 0`` (in float32 at ``x = 1e-4`` its gradient is off by a factor of four).
    Above, ``sin(y) / y`` with the divisor kept away from 0 in the unused branch so that
    no NaN reaches a gradient.
    """
    x = jnp.asarray(x)
    y = math.pi * x
    small = jnp.abs(y) < _SINC_SERIES_BELOW
    y_safe = jnp.where(small, 1.0, y)
    direct = jnp.sin(y_safe) / y_safe
    y2 = y * y
    series = jnp.ones_like(y2)
    for k in range(_SINC_TERMS, 0, -1):
        series = 1.0 - y2 / ((2 * k) * (2 * k + 1)) * series
    return jnp.where(small, series, direct)


def envelopes(width_px, freq: Float[Array, " m"]) -> Float[Array, "n m"]:
    """``w sinc(f w)`` per interval: computed once per distinct width (eq. 13), then spread.

    Widths given as a traced array (a plan passed into a compiled function) are computed
    one per interval.
    """
    if not isinstance(width_px, np.ndarray):
        w = jnp.asarray(width_px, freq.dtype)[:, None]
        return w * sinc(freq[None, :] * w)
    widths, which = np.unique(width_px, return_inverse=True)
    w = jnp.asarray(widths, freq.dtype)[:, None]
    return (w * sinc(freq[None, :] * w))[which.reshape(-1)]


def phases(
    centre_px: np.ndarray, axis: FreqAxis
) -> tuple[Float[Array, "n m"], Float[Array, "n m"]]:
    """``cos`` and ``sin`` of ``2 pi c f`` for centres `c` and the frequencies of `axis`.

    Each ``k = B q + r`` (``B ~ sqrt(max k)``): the angles of ``c r step`` and of ``c B q
    step`` are tabulated and the entries are their sums (one complex product each),
    about ``2 sqrt(m)`` sines per interval instead of ``2 m``: on a CPU the sines cost
    more than the matrix product they feed. An offset adds one angle per interval.
    """
    index, step = np.asarray(axis.index), axis.step
    if index.size and index.min() < 0:
        raise ValueError("phase indices must be >= 0")
    span = int(index.max()) + 1 if index.size else 1
    base = max(1, math.isqrt(span - 1) + 1)
    c = jnp.asarray(centre_px, step.dtype)[:, None]
    fine = (2.0 * math.pi) * (c * (jnp.arange(base, dtype=step.dtype) * step))
    coarse = (2.0 * math.pi) * (
        c * (jnp.arange((span - 1) // base + 1, dtype=step.dtype) * (base * step))
    )
    # The tables are put in memory: fused into the outer product below, XLA recomputed
    # every sine per entry (25 ms instead of 1.4 for 629 x 513).
    angles = jnp.concatenate([fine, coarse], axis=1)
    trig = materialise(jnp.stack([jnp.cos(angles), jnp.sin(angles)]))
    fc, cc = trig[0, :, None, :base], trig[0, :, base:, None]
    fs, cs = trig[1, :, None, :base], trig[1, :, base:, None]
    # Every k = 0 .. span - 1 as an outer product (no gather), then the indices asked for.
    n = fine.shape[0]
    cos = (cc * fc - cs * fs).reshape(n, -1)[:, :span]
    sin = (cs * fc + cc * fs).reshape(n, -1)[:, :span]
    if not np.array_equal(index, np.arange(span)):
        cos, sin = cos[:, index], sin[:, index]
    if axis.offset is not None:
        shift = (2.0 * math.pi) * (c * axis.offset)
        sc, ss = jnp.cos(shift), jnp.sin(shift)
        cos, sin = cos * sc - sin * ss, sin * sc + cos * ss
    return cos, sin


def box_kernel(
    centre_px: np.ndarray, width_px: np.ndarray, axis: FreqAxis, params
) -> tuple[Float[Array, "n m"], Float[Array, "n m"]]:
    """Far-field (Fraunhofer) axis kernel: ``w sinc(f w) (cos, sin)(2 pi f c)``."""
    env = envelopes(width_px, axis.freq(axis.step.dtype))
    cos, sin = phases(centre_px, axis)
    return env * cos, env * sin


def _segment_sum(values: Array, segments: np.ndarray, n: int) -> Array:
    return jax.ops.segment_sum(
        values, jnp.asarray(segments), num_segments=n, indices_are_sorted=True
    )


def matmul(a: Array, b: Array) -> Array:
    """``a @ b``, with complex products as three real ones (Gauss's trick).

    XLA's complex64 matrix product on the CPU took 38.6 ms for the near field's
    ``(513, 1215) @ (1215, 1026)`` (the heptagon at 1024 px) where the three real products
    ``ac``, ``bd`` and ``(a + b)(c + d)`` took 22.0 ms (four real products: 27.4 ms);
    the result differs by rounding (1.5e-6 of the largest value in float32, from the
    subtraction ``(a + b)(c + d) - ac - bd``).
    """
    a_cplx, b_cplx = jnp.iscomplexobj(a), jnp.iscomplexobj(b)
    if not (a_cplx or b_cplx):
        return a @ b
    if not b_cplx:
        return jax.lax.complex(a.real @ b, a.imag @ b)
    if not a_cplx:
        return jax.lax.complex(a @ b.real, a @ b.imag)
    ar, ai, br, bi = a.real, a.imag, b.real, b.imag
    rr, ii = ar @ br, ai @ bi
    return jax.lax.complex(rr - ii, (ar + ai) @ (br + bi) - rr - ii)


def _tiled_products(
    kernel_t: Array, inners: list[Array], tiles: Tiles, shape: tuple[int, int]
) -> list[Array]:
    """``kernel_t @ inner`` for each inner, only where `tiles` keeps it (zeros elsewhere).

    Kept tiles are gathered into bands of :data:`BAND_TILES` tile rows and runs of kept tile
    columns within a band (gaps of up to :data:`GAP_TILES` tiles bridged): each run is one
    ordinary matrix product, and the image is assembled by concatenation. (One small
    product per 8 x 8 tile, batched, ran 5-10 times slower than the dense product.)
    """
    dtype = jnp.result_type(kernel_t, *inners)
    bands: dict[tuple[int, int], list] = {}
    for r0, r1, c0, c1 in tile_runs(tiles, shape):
        bands.setdefault((r0, r1), []).append((c0, c1))
    k = len(inners)
    # All inners side by side: one product per run, as in the dense evaluation.
    stacked = jnp.stack(inners, axis=1)  # (R, k, nx)
    rows = [[] for _ in range(k)]
    done = 0
    for (r0, r1), runs in sorted(bands.items()):
        if r0 > done:
            for j in range(k):
                rows[j].append(jnp.zeros((r0 - done, shape[1]), dtype))
        pieces = [[] for _ in range(k)]
        col = 0
        for c0, c1 in runs:
            if c0 > col:
                for j in range(k):
                    pieces[j].append(jnp.zeros((r1 - r0, c0 - col), dtype))
            block = stacked[:, :, c0:c1].reshape(stacked.shape[0], -1)
            prod = matmul(kernel_t[r0:r1], block).astype(dtype).reshape(r1 - r0, k, c1 - c0)
            for j in range(k):
                pieces[j].append(prod[:, j])
            col = c1
        for j in range(k):
            if col < shape[1]:
                pieces[j].append(jnp.zeros((r1 - r0, shape[1] - col), dtype))
            rows[j].append(jnp.concatenate(pieces[j], axis=1))
        done = r1
    out = []
    for j in range(k):
        if done < shape[0]:
            rows[j].append(jnp.zeros((shape[0] - done, shape[1]), dtype))
        out.append(jnp.concatenate(rows[j], axis=0))
    return out


#: Tile rows per band of the culled evaluation, and the widest gap (in tiles) bridged.
BAND_TILES = 8
GAP_TILES = 4


def tile_runs(tiles: Tiles, shape: tuple[int, int]) -> list[tuple[int, int, int, int]]:
    """The rectangles ``(row0, row1, col0, col1)`` (pixels) one culled evaluation computes."""
    t = tiles.size
    n_ty, n_tx = -(-shape[0] // t), -(-shape[1] // t)
    mask = np.zeros((n_ty, n_tx), bool)
    mask[tiles.rows, tiles.cols] = True
    runs = []
    for b0 in range(0, n_ty, BAND_TILES):
        cols = np.nonzero(mask[b0 : b0 + BAND_TILES].any(axis=0))[0]
        if cols.size == 0:
            continue
        breaks = np.nonzero(np.diff(cols) > GAP_TILES + 1)[0]
        starts = np.concatenate([[cols[0]], cols[breaks + 1]])
        ends = np.concatenate([cols[breaks], [cols[-1]]])
        r0, r1 = b0 * t, min(shape[0], (b0 + BAND_TILES) * t)
        runs += [
            (r0, r1, s * t, min(shape[1], (e + 1) * t)) for s, e in zip(starts, ends, strict=True)
        ]
    return runs


class Tiles(NamedTuple):
    """Output tiles kept by culling: `size` pixels a side, at tile rows `rows`, cols `cols`."""

    size: int
    rows: np.ndarray
    cols: np.ndarray


def _terms(
    plan: QuadPlan,
    kernel: Kernel,
    skip_x: bool,
    skip_y: bool,
    tiles: Tiles | None,
    index_y: np.ndarray,
    index_x: np.ndarray,
    amplitudes: Array,
    step: Array,
    offsets: tuple[Array, Array] | None,
    params,
) -> tuple[Array, Array, Array, Array]:
    dtype = amplitudes.dtype
    off_y, off_x = (None, None) if offsets is None else offsets
    axis_y = FreqAxis(index_y, step, off_y)
    axis_x = FreqAxis(index_x, step, off_x)
    ex, ox = kernel(plan.col_c, plan.col_s, axis_x, params)
    ey, oy = kernel(plan.row_c, plan.row_s, axis_y, params)
    rows, col = plan.n_rows, plan.quad_col
    sx = jnp.asarray(plan.sign_x, dtype)
    sy = jnp.asarray(plan.sign_y, dtype)
    shape = (index_y.size, index_x.size)
    # inner(w, j): the sums over each row's quads of w times column kernel j (0: even, 1: odd).
    if plan.dense_inner:
        kernels_x = (ex, ox)

        def inner(weights, j):
            p = jnp.zeros((rows, plan.n_cols), dtype).at[plan.quad_row, col].add(weights)
            return matmul(p, kernels_x[j])

    else:
        # Each quad's kernel row, gathered on its own: fused into the kernel's arithmetic
        # or into the amplitudes' product, XLA's CPU gather ran per element (the
        # heptagon's far field at 1024 px: 8.8 ms, now 7.4).
        per_quad = [materialise(materialise(k)[col]) for k in ((ex,) if skip_x else (ex, ox))]

        def inner(weights, j):
            return _segment_sum(weights[:, None] * per_quad[j], plan.quad_row, rows)

    def products(kernel_y, inners):
        if tiles is not None:
            return _tiled_products(kernel_y.T, inners, tiles, shape)
        out = matmul(kernel_y.T, jnp.concatenate(inners, axis=1))
        return jnp.split(out, len(inners), axis=1)

    # Inner sums over the quads of each row: [P_ee Ex | P_eo Ox] and [P_oe Ex | P_oo Ox].
    a = amplitudes
    even_in = [inner(a, 0)]
    if not skip_x:
        even_in.append(inner(a * sx, 1))
    blocks = products(ey, even_in)
    zeros = jnp.zeros(shape, blocks[0].dtype)
    t1 = blocks[0]
    t2 = blocks[1] if not skip_x else zeros
    if skip_y:
        return t1, t2, zeros, zeros
    odd_in = [inner(a * sy, 0)]
    if not skip_x:
        odd_in.append(inner(a * (sx * sy), 1))
    blocks = products(oy, odd_in)
    return t1, t2, blocks[0], (blocks[1] if not skip_x else zeros)


class _Static:
    """A numpy value as a hashable static argument (compared by its bytes)."""

    def __init__(self, value):
        self.value = value
        leaves = value if isinstance(value, tuple) else (value,)
        self._key = tuple(
            (np.asarray(v).shape, np.asarray(v).tobytes()) if v is not None else None
            for v in leaves
        )

    def __hash__(self):
        return hash(self._key)

    def __eq__(self, other):
        return isinstance(other, _Static) and other._key == self._key


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2, 3, 4))
def _accelerated_terms(plan, kernel, tiles, index_y, index_x, amplitudes, step, offsets, params):
    tiles = None if tiles.value is None else Tiles(*tiles.value)
    return _terms(
        plan, kernel, plan.mirror_x, plan.mirror_y, tiles, index_y.value, index_x.value,
        amplitudes, step, offsets, params,
    )  # fmt: skip


@_accelerated_terms.defjvp
def _accelerated_terms_jvp(plan, kernel, tiles, index_y, index_x, primals, tangents):
    # The value skips the terms the mirrors make zero and the culled tiles; the derivative
    # is that of the whole transform.
    full = functools.partial(_terms, plan, kernel, False, False, None, index_y.value, index_x.value)
    return jax.jvp(full, primals, tangents)


def parity_terms(
    plan: QuadPlan,
    kernel: Kernel,
    amplitudes: Float[Array, " k"],
    step: Float[Array, ""],
    index_y: np.ndarray,
    index_x: np.ndarray,
    params=None,
    *,
    offsets: tuple[Array, Array] | None = None,
    tiles: Tiles | None = None,
) -> tuple[Array, Array, Array, Array]:
    """``(T_1, T_2, T_3, T_4)`` on the grid of frequencies ``index * step (+ offsets)``.

    `amplitudes` are in the plan's quad order; `step` and the `offsets` (y, x) in cycles
    per pixel; the indices are integers >= 0 (static). Terms a mirror of the plan makes
    zero are zeros in the value, and so are the tiles `tiles` does not keep; the
    derivative is always that of the whole transform.
    """
    if not (plan.mirror_x or plan.mirror_y or tiles is not None):
        return _terms(
            plan, kernel, False, False, None, index_y, index_x, amplitudes, step, offsets,
            params,
        )  # fmt: skip
    return _accelerated_terms(
        plan, kernel, _Static(None if tiles is None else tuple(tiles)), _Static(index_y),
        _Static(index_x), amplitudes, step, offsets, params,
    )  # fmt: skip


def quadrant_terms(
    plan: QuadPlan,
    kernel: Kernel,
    amplitudes: Float[Array, " k"],
    step_px: Float[ArrayLike, ""],
    npix: int,
    params=None,
    tiles: Tiles | None = None,
) -> tuple[Array, Array, Array, Array]:
    """:func:`parity_terms` on the quadrant of an `npix` output of pixel `step_px` (only on
    `tiles` when given): the far and the near field differ only in `kernel` and `params`."""
    dtype = amplitudes.dtype
    step = jnp.asarray(step_px, dtype)
    params = None if params is None else jnp.asarray(params, dtype)
    index = quadrant_index(npix)
    return parity_terms(plan, kernel, amplitudes, step, index, index, params, tiles=tiles)


def far_field_quadrants(
    terms: tuple[Array, Array, Array, Array],
) -> tuple[Array, Array]:
    """``|F|^2`` on the quadrant for the sign pairs (+, +) and (+, -) of ``(f_y, f_x)``.

    ``F = T_1 - i sx T_2 - i sy T_3 - sx sy T_4`` with real terms; (-, -) equals (+, +)
    and (-, +) equals (+, -) (a real aperture's intensity is point symmetric).
    """
    t1, t2, t3, t4 = terms
    same = (t1 - t4) ** 2 + (t2 + t3) ** 2
    opposite = (t1 + t4) ** 2 + (t2 - t3) ** 2
    return same, opposite


def quadrant_index(n: int) -> np.ndarray:
    """Frequency indices ``0 .. n // 2`` of the quadrant of an ``n``-pixel output."""
    return np.arange(n // 2 + 1)


def unfold(n: int, pp: Array, pm: Array, mp: Array | None = None, mm: Array | None = None) -> Array:
    """The ``n x n`` image from its quadrant images for ``(sign f_y, sign f_x)`` pairs.

    Arguments are (+, +), (+, -), (-, +), (-, -); the last two default to (+, -) and
    (+, +) (point symmetry). Output pixel ``k`` is at frequency index ``k - n // 2``.
    """
    mp = pm if mp is None else mp
    mm = pp if mm is None else mm
    h = n // 2

    def row(neg_x, pos_x):
        return jnp.concatenate([neg_x[:, h:0:-1], pos_x[:, : n - h]], axis=1)

    top = row(mm, mp)[h:0:-1]
    bottom = row(pm, pp)[: n - h]
    return jnp.concatenate([top, bottom], axis=0)
