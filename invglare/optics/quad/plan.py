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

import numpy as np

from invglare.optics.quad.quadtree import QuadLayout

#: Largest asymmetry (relative to the raster's largest value) still called a symmetry.
MIRROR_TOLERANCE = 1e-4


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
    mirror partner must be zero. Equal to `tolerance` times the largest absolute value.
    """
    arr = np.asarray(raster, dtype=np.float64)
    limit = tolerance * float(np.max(np.abs(arr)))
    return (
        bool(np.max(np.abs(arr - _mirrored(arr, 1))) <= limit),
        bool(np.max(np.abs(arr - _mirrored(arr, 0))) <= limit),
    )


@dataclasses.dataclass(frozen=True, eq=False)
class QuadPlan:
    """The evaluation plan of a :class:`~invglare.optics.quad.quadtree.QuadLayout`.

    **Fields:** the `layout`; `mirror_x` / `mirror_y` (the aperture is even in x / in y:
    the transform's odd parts along that axis are zero and skipped); the distinct
    intervals up to sign, `row_c` >= 0, `row_s` (centre and height, px, about the grid
    origin) and `col_c`, `col_s`; per quad (in the order `order` of the layout's quads,
    rows sorted) its `quad_row`, `quad_col` and the signs of its centre, `sign_y` and
    `sign_x` (-1, 0 or +1). Hashable by content (a static field of a Module).
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
    digest: str = dataclasses.field(default="", repr=False)

    def __post_init__(self):
        if not self.digest:
            h = hashlib.sha1(self.layout.digest.encode())
            h.update(repr((self.mirror_x, self.mirror_y)).encode())
            object.__setattr__(self, "digest", h.hexdigest())

    def __hash__(self) -> int:
        return hash(self.digest)

    def __eq__(self, other) -> bool:
        return isinstance(other, QuadPlan) and other.digest == self.digest

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


def make_plan(layout: QuadLayout, mirror_x: bool = False, mirror_y: bool = False) -> QuadPlan:
    """The plan of a layout: its distinct intervals, the mirrors whose odd terms are skipped.

    Pass the mirrors of the raster (:func:`detect_mirrors`) only when it has them: with a
    mirror the value of the transform keeps only the part even along that axis.
    """
    rows, cols = layout.shape
    row_c, row_s, quad_row, sign_y = _intervals(layout.y0, layout.h, rows // 2)
    col_c, col_s, quad_col, sign_x = _intervals(layout.x0, layout.w, cols // 2)
    order = np.argsort(quad_row, kind="stable")
    return QuadPlan(
        layout=layout,
        mirror_x=bool(mirror_x),
        mirror_y=bool(mirror_y),
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
