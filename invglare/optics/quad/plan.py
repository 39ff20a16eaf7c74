"""How a quad layout is evaluated: its distinct intervals, its symmetries, its culled tiles.

A :class:`QuadPlan` is decided on concrete values, once (like the layout it is made of):
the distinct row and column intervals of the quads (the rows and columns of the sparse
amplitude matrix of :func:`invglare.optics.quad.transform.separable_sum`), the mirror
symmetries of the aperture (:func:`detect_mirrors`), and optionally which output tiles
are culled (:mod:`invglare.optics.quad.cull`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from types import SimpleNamespace
from typing import NamedTuple

import numpy as np
from jaxtyping import Array

from invglare.optics.quad.quadtree import DigestIdentity, QuadLayout

#: Largest odd part still called a symmetry: its sum of absolute values over the raster's
#: (see :func:`detect_mirrors`).
MIRROR_TOLERANCE = 1e-6


def _mirrored(arr: np.ndarray, axis: int) -> np.ndarray:
    """`arr` mirrored about index ``size // 2`` of `axis` (the grid origin), zero-filled."""
    size = arr.shape[axis]
    src = 2 * (size // 2) - np.arange(size)
    ok = (src >= 0) & (src < size)
    out = np.zeros_like(arr)
    if axis == 0:
        out[ok] = arr[src[ok]]
    else:
        out[:, ok] = arr[:, src[ok]]
    return out


def detect_mirrors(raster, tolerance: float = MIRROR_TOLERANCE) -> tuple[bool, bool]:
    """Whether a raster is symmetric under ``x -> -x`` and under ``y -> -y`` (about 0).

    The grid origin is pixel ``n // 2`` (see :mod:`invglare._core.grids`); values without a
    mirror partner count as asymmetric. An axis is a mirror when the raster's odd part
    ``o = (t - t_mirrored) / 2`` is small in sum: ``sum |o| <= tolerance * sum |t|``.

    Why a sum and not the largest pixel: skipping the odd part changes the transform at
    any frequency by at most ``sum |o|``, and the transform's peak of a non-negative
    raster is ``sum t``, so the far or near field moves by at most ``2 * tolerance`` of
    its peak intensity wherever the mirror is used. Rounding of a float32 soft raster is
    not a reason to lose the mirror: invglare's own coverage rasters of symmetric shapes
    differ from their mirror images by up to 1.2e-4 per edge pixel at 1024 px (2.3e-4 at
    2048), far below the bound in sum (their odd parts are below 1e-7 of the raster's sum).
    """
    arr = np.asarray(raster, dtype=np.float64)
    limit = 2.0 * tolerance * float(np.sum(np.abs(arr)))
    return (
        bool(np.sum(np.abs(arr - _mirrored(arr, 1))) <= limit),
        bool(np.sum(np.abs(arr - _mirrored(arr, 0))) <= limit),
    )


@dataclasses.dataclass(frozen=True, eq=False)
class QuadPlan(DigestIdentity):
    """The evaluation plan of a :class:`~invglare.optics.quad.quadtree.QuadLayout`.

    **Fields:** the `layout`; `mirror_x` / `mirror_y` (the aperture is even in x / in y:
    the transform's odd parts along that axis are zero and skipped); the distinct
    intervals up to sign, `row_c` >= 0, `row_s` (centre and height, px, about the grid
    origin) and `col_c`, `col_s`; per quad (in the order `order` of the layout's quads,
    rows sorted) its `quad_row`, `quad_col` and the signs of its centre, `sign_y` and
    `sign_x` (-1, 0 or +1); `dense_inner`: the amplitudes are summed into a dense
    ``rows x cols`` matrix and multiplied by the column kernel, instead of gathered per
    quad (for plans whose matrix is small next to their entries, as the corner plans of
    :func:`invglare.optics.quad.nearfield.corner_plan`). Hashable by content (a static
    field of a Module).
    """

    layout: QuadLayout
    mirror_x: bool
    mirror_y: bool
    row_c: np.ndarray
    row_s: np.ndarray
    col_c: np.ndarray
    col_s: np.ndarray
    quad_row: np.ndarray
    quad_col: np.ndarray
    sign_y: np.ndarray
    sign_x: np.ndarray
    order: np.ndarray
    dense_inner: bool = False
    digest: str = dataclasses.field(default="", repr=False)

    def __post_init__(self):
        if not self.digest:
            h = hashlib.sha1(self.layout.digest.encode())
            h.update(repr((self.mirror_x, self.mirror_y)).encode())
            if self.dense_inner:
                h.update(b"dense")
            object.__setattr__(self, "digest", h.hexdigest())

    @property
    def n_rows(self) -> int:
        return int(self.row_c.shape[0])

    @property
    def n_cols(self) -> int:
        return int(self.col_c.shape[0])


def _intervals(start: np.ndarray, size: np.ndarray, origin: int):
    """Distinct intervals up to sign (|centre|, size) in px about `origin`; each quad's
    index among them and the sign of its centre."""
    twice_centre = 2 * start + size - 1 - 2 * origin  # exact integers
    keys = np.stack([np.abs(twice_centre), size], axis=1)
    distinct, index = np.unique(keys, axis=0, return_inverse=True)
    centre = distinct[:, 0] / 2.0
    return centre, distinct[:, 1].astype(np.float64), index.reshape(-1), np.sign(twice_centre)


def make_plan(
    layout: QuadLayout,
    mirror_x: bool = False,
    mirror_y: bool = False,
    origin: tuple[int, int] | None = None,
) -> QuadPlan:
    """The plan of a layout: its distinct intervals, the mirrors whose odd terms are skipped.

    Pass the mirrors of the raster (:func:`detect_mirrors`) only when it has them: with a
    mirror the value of the transform keeps only the part even along that axis. `origin`
    is the (row, col) of the grid origin in the layout's raster (default its centre pixel
    ``shape // 2``; another for a layout of a crop).
    """
    rows, cols = layout.shape
    origin = (rows // 2, cols // 2) if origin is None else origin
    parts = plan_arrays(layout.x0, layout.y0, layout.w, layout.h, origin)
    return QuadPlan(layout=layout, mirror_x=bool(mirror_x), mirror_y=bool(mirror_y), **parts)


def plan_arrays(x0, y0, w, h, origin: tuple[int, int]) -> dict[str, np.ndarray]:
    """The interval arrays of quads given as pixel rectangles (see :class:`QuadPlan`)."""
    row_c, row_s, quad_row, sign_y = _intervals(np.asarray(y0), np.asarray(h), origin[0])
    col_c, col_s, quad_col, sign_x = _intervals(np.asarray(x0), np.asarray(w), origin[1])
    order = np.argsort(quad_row, kind="stable")
    return dict(
        row_c=row_c,
        row_s=row_s,
        col_c=col_c,
        col_s=col_s,
        quad_row=quad_row[order],
        quad_col=quad_col[order],
        sign_y=sign_y[order].astype(np.float64),
        sign_x=sign_x[order].astype(np.float64),
        order=order,
    )


class DynamicPlan(NamedTuple):
    """A plan whose arrays are arguments of a compiled function, not constants in it.

    Frame-by-frame layouts (progressive refinement) differ every frame; padded to bucket
    sizes (:func:`dynamic_plan`), they share one compiled evaluation per bucket.
    """

    row_c: Array
    row_s: Array
    col_c: Array
    col_s: Array
    quad_row: Array
    quad_col: Array
    sign_y: Array
    sign_x: Array

    @property
    def n_rows(self) -> int:
        return int(self.row_c.shape[0])

    @property
    def n_cols(self) -> int:
        return int(self.col_c.shape[0])

    @property
    def dense_inner(self) -> bool:
        """Whether the quads are summed into a dense matrix (see :class:`QuadPlan`): when it
        has at most :data:`DENSE_PER_QUAD` entries per quad (decided on the padded shapes,
        static under `jit`)."""
        return self.n_rows * self.n_cols <= DENSE_PER_QUAD * int(self.quad_row.shape[0])


#: A dynamic plan's quads are summed into a dense ``rows x cols`` matrix when it has at
#: most this many entries per quad: a gathered kernel row costs as much as tens of rows of
#: the dense product (a progressive frame of the benchmark's shadow over the box, 1024 px
#: raster to a 2048 px output, 4 102 pixel quads: 65 ms gathered, 20 ms dense).
DENSE_PER_QUAD = 64


def bucket(n: int, smallest: int = 64) -> int:
    """The padded size of `n`: the next power of two, at least `smallest`."""
    return max(smallest, 1 << max(0, math.ceil(math.log2(max(n, 1)))))


def dynamic_plan(plan, amplitudes: np.ndarray) -> tuple[DynamicPlan, np.ndarray]:
    """A plan (a :class:`QuadPlan` or the dict of :func:`plan_arrays`) as padded arrays,
    with its amplitudes (in the plan's order) padded by 0.

    Padding quads have amplitude 0; padding rows and columns are unit intervals at 0.
    """
    if isinstance(plan, dict):
        plan = SimpleNamespace(**plan, n_rows=plan["row_c"].size, n_cols=plan["col_c"].size)
    k, r, c = plan.quad_row.size, plan.n_rows, plan.n_cols
    kb, rb, cb = bucket(k), bucket(r), bucket(c)

    def pad(a, n, value):
        return np.concatenate([a, np.full(n - a.size, value, dtype=a.dtype)])

    dyn = DynamicPlan(
        row_c=pad(plan.row_c, rb, 0.0),
        row_s=pad(plan.row_s, rb, 1.0),
        col_c=pad(plan.col_c, cb, 0.0),
        col_s=pad(plan.col_s, cb, 1.0),
        # Padding quads go to the last row, keeping the rows sorted.
        quad_row=pad(plan.quad_row, kb, rb - 1),
        quad_col=pad(plan.quad_col, kb, 0),
        sign_y=pad(plan.sign_y, kb, 0.0),
        sign_x=pad(plan.sign_x, kb, 0.0),
    )
    return dyn, pad(np.asarray(amplitudes, np.float64), kb, 0.0)
