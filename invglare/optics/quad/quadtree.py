"""Quads from a raster: the bottom-up quadtree of Scandolo, Lee & Eisemann (2018, sec. 4.2).

The raster is read on concrete values (numpy, outside `jit`): the *structure* (which quads,
where, of which sign) depends on the data, so it is decided once, here. What the quads
transform is a linear function of the raster's values (:meth:`QuadLayout.intensities`),
so the transform of a layout is a pure JAX function through which gradients flow.

**The tree** (fig. 2 of the paper). Cells start at the *base level* (pixels, or blocks of
``2**base_level`` pixels holding their mean: the paper starts at half the input size,
``base_level = 1``, an approximation) and are merged level by level. A cell is *uniform*
(all of it has one value, not yet emitted) or *mixed* (its content is already in the quad
list). For each 2 x 2 block of children:

- four uniform children with one value: the parent is uniform with that value;
- three uniform children with one non-zero value ``v``: the parent is uniform ``v`` and a
  *negative* quad of value ``v`` cancels it over the fourth child (whose own content, if
  any, is emitted as usual);
- otherwise the parent is mixed, and the non-zero uniform children are emitted, two
  adjacent ones with the same value as one 2:1 (non-square) quad.

A uniform non-zero cell that reaches the top is emitted whole.

**Soft rasters.** invglare's rasters are anti-aliased: edge pixels hold fractional
coverage. Each quad carries an intensity, read from the raster as the mean over a *group*
of pixels: the pixels of one value (all the fully open ones, say) form one group; the
*unique* cells, the fractional ones and those within `band` cells of them, are never
merged and are each their own group. The layout therefore reproduces the raster exactly
at the values it was built on, and the derivative of the transform with respect to a
unique pixel is exactly that pixel's own transform (where a shape's parameters move the
raster, which is at its edges). Far from the band, a pixel shares its gradient with its
group; :meth:`QuadLayout.departure` measures how far a new raster is from one the layout
represents.

**Sizes.** The tree needs a square power-of-two raster: another shape is padded with zeros
(which changes nothing in the transform: the quads keep the raster's own coordinates) and
:attr:`QuadLayout.note` says so.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from invglare.errors import InputDataError, PhysicsRangeError

log = logging.getLogger("invglare")

#: Largest raster side the tree accepts (the paper's largest is 4096).
MAX_SIDE = 16384
#: Up to this many shared-value groups, intensities are masked sums (else a scatter).
_DENSE_GROUPS = 8


class DigestIdentity:
    """Equal and hashed by `digest` (layouts and plans are static arguments of compiled
    functions: their arrays would be compared element by element otherwise)."""

    digest: str

    def __hash__(self) -> int:
        return hash(self.digest)

    def __eq__(self, other) -> bool:
        return type(other) is type(self) and other.digest == self.digest


def grown_by_one(mask: np.ndarray) -> np.ndarray:
    """`mask` with its four-neighbours set too."""
    grown = mask.copy()
    grown[1:] |= mask[:-1]
    grown[:-1] |= mask[1:]
    grown[:, 1:] |= mask[:, :-1]
    grown[:, :-1] |= mask[:, 1:]
    return grown


@dataclasses.dataclass(frozen=True, eq=False)
class QuadLayout(DigestIdentity):
    """The quads of one raster, and how their intensities are read from a raster.

    Quads are in the raster's pixel indices: quad ``k`` covers rows ``y0[k] .. y0[k] +
    h[k] - 1`` and columns ``x0[k] .. x0[k] + w[k] - 1``, with sign ``sign[k]`` (+1, or -1
    for a negative quad) and intensity ``intensities(raster)[group[k]]``.

    **Fields:** `shape` (rows, cols) of the raster; `side`, the padded square it was built
    on; `base_level` (cells of ``2**base_level`` pixels); `band`; the per-quad arrays `x0`,
    `y0`, `w`, `h` (int), `sign` (+1.0 / -1.0), `group` (int); per base cell of the padded
    raster its `cell_group` (-1 where no quad reads the cell: its value was 0), groups
    ``0 .. n_unique - 1`` being the unique cells in raster order; `group_cells`, the cells
    in each group; `note`, what was done to the input (padding), or "".

    A layout is hashable by its content, so it can be a static field of an equinox Module.
    """

    shape: tuple[int, int]
    side: int
    base_level: int
    band: int | None
    x0: np.ndarray
    y0: np.ndarray
    w: np.ndarray
    h: np.ndarray
    sign: np.ndarray
    group: np.ndarray
    cell_group: np.ndarray
    n_unique: int
    group_cells: np.ndarray
    note: str = ""
    digest: str = dataclasses.field(default="", repr=False)

    def __post_init__(self):
        if not self.digest:
            h = hashlib.sha1()
            h.update(repr((self.shape, self.side, self.base_level, self.band)).encode())
            for a in (self.x0, self.y0, self.w, self.h, self.sign, self.group, self.cell_group):
                h.update(np.ascontiguousarray(a).tobytes())
            object.__setattr__(self, "digest", h.hexdigest())

    @property
    def n_quads(self) -> int:
        return int(self.x0.shape[0])

    @property
    def n_groups(self) -> int:
        return int(self.group_cells.shape[0])

    @property
    def cell(self) -> int:
        return 1 << self.base_level

    def counts(self) -> dict[str, int]:
        """Quads in all, negative ones, non-square ones, and distinct sizes."""
        sizes = {(int(a), int(b)) for a, b in zip(self.w, self.h, strict=True)}
        return {
            "quads": self.n_quads,
            "negative": int(np.sum(self.sign < 0)),
            "non_square": int(np.sum(self.w != self.h)),
            "sizes": len(sizes),
        }

    def _cell_means(self, raster: Float[Array, "rows cols"]) -> Float[Array, "m m"]:
        if tuple(raster.shape) != self.shape:
            raise InputDataError(
                f"this quad layout was built for a {self.shape[0]}x{self.shape[1]} raster, "
                f"got shape {tuple(raster.shape)}"
            )
        rows, cols = self.shape
        if (rows, cols) != (self.side, self.side):
            raster = jnp.pad(raster, ((0, self.side - rows), (0, self.side - cols)))
        c, m = self.cell, self.side // self.cell
        return raster if c == 1 else raster.reshape(m, c, m, c).mean(axis=(1, 3))

    def intensities(self, raster: Float[Array, "rows cols"]) -> Float[Array, " groups"]:
        """Each group's intensity: the mean of its cells' means (linear in the raster)."""
        means = self._cell_means(raster)
        flat = means.reshape(-1)
        groups = self.cell_group.reshape(-1)
        unique = flat[np.flatnonzero((groups >= 0) & (groups < self.n_unique))]
        shared = range(self.n_unique, self.n_groups)
        if len(shared) <= _DENSE_GROUPS:
            # A masked sum over the cells per shared value: far cheaper than a scatter.
            sums = [jnp.sum(jnp.where(self.cell_group == g, means, 0.0)) for g in shared]
            shared_sum = jnp.stack(sums) if sums else jnp.zeros((0,), means.dtype)
        else:
            used = np.flatnonzero(groups >= self.n_unique)
            shared_sum = jax.ops.segment_sum(
                flat[used], jnp.asarray(groups[used] - self.n_unique), num_segments=len(shared)
            )
        counts = jnp.asarray(self.group_cells[self.n_unique :], means.dtype)
        return jnp.concatenate([unique, shared_sum / counts])

    def intensities_numpy(self, raster: np.ndarray) -> np.ndarray:
        """:meth:`intensities` of a concrete raster in numpy (for loops over frames)."""
        arr = np.asarray(raster, dtype=np.float64)
        rows, cols = self.shape
        padded = np.zeros((self.side, self.side))
        padded[:rows, :cols] = arr
        c, m = self.cell, self.side // self.cell
        means = padded if c == 1 else padded.reshape(m, c, m, c).mean(axis=(1, 3))
        groups = self.cell_group.reshape(-1)
        used = groups >= 0
        sums = np.bincount(groups[used], weights=means.reshape(-1)[used], minlength=self.n_groups)
        return sums / self.group_cells

    def amplitudes(self, levels: Float[Array, " groups"]) -> Float[Array, " quads"]:
        """Signed intensity of every quad, ``sign * levels[group]``, from :meth:`intensities`."""
        return levels[jnp.asarray(self.group)] * jnp.asarray(self.sign, dtype=levels.dtype)

    def transmission(self, levels: Float[Array, " groups"]) -> Float[Array, ""]:
        """``sum |f|`` over pixels of the represented raster: the power through it in
        aperture pixels, a PSF's divisor (see :mod:`invglare.optics.fraunhofer`)."""
        weight = jnp.asarray(self.group_cells * self.cell * self.cell, levels.dtype)
        return jnp.sum(weight * jnp.abs(levels))

    def represented(self, raster: Float[Array, "rows cols"]) -> Float[Array, "rows cols"]:
        """The raster the quads stand for: each pixel replaced by its group's intensity."""
        levels = self.intensities(raster)
        padded = jnp.concatenate([levels, jnp.zeros((1,), levels.dtype)])
        cells = padded[jnp.asarray(self.cell_group)]
        c = self.cell
        pixels = cells if c == 1 else jnp.repeat(jnp.repeat(cells, c, axis=0), c, axis=1)
        return pixels[: self.shape[0], : self.shape[1]]

    def departure(self, raster: Float[Array, "rows cols"]) -> Float[Array, ""]:
        """Largest difference between a cell's mean and what the quads give it.

        Zero (to round-off) for the raster the layout was built on; a raster whose values
        changed inside a group (a shape that moved beyond the band), or became non-zero
        where no quad reads it, departs.
        """
        means = self._cell_means(raster)
        levels = self.intensities(raster)
        padded = jnp.concatenate([levels, jnp.zeros((1,), levels.dtype)])
        return jnp.max(jnp.abs(means - padded[jnp.asarray(self.cell_group)]))


def _check_raster(raster) -> np.ndarray:
    arr = np.asarray(raster)
    if arr.ndim != 2:
        raise InputDataError(f"a quadtree needs a 2-D raster, got shape {arr.shape}")
    if arr.size == 0:
        raise InputDataError(f"the raster is empty (shape {arr.shape})")
    if not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr):
        raise InputDataError(f"a quadtree needs a real raster, got dtype {arr.dtype}")
    if max(arr.shape) > MAX_SIDE:
        raise PhysicsRangeError(
            f"raster of {arr.shape[0]}x{arr.shape[1]} pixels is larger than the {MAX_SIDE} "
            "pixels a side the quadtree accepts"
        )
    if not np.all(np.isfinite(arr)):
        raise InputDataError("the raster holds non-finite values")
    if not np.any(arr != 0):
        raise InputDataError(
            "the aperture is empty: the raster is zero everywhere, so it has no quads and "
            "no far field to normalise"
        )
    return arr.astype(np.float64)


def _padded(arr: np.ndarray) -> tuple[np.ndarray, str]:
    rows, cols = arr.shape
    side = 1 << max(0, math.ceil(math.log2(max(rows, cols))))
    if (rows, cols) == (side, side):
        return arr, ""
    out = np.zeros((side, side))
    out[:rows, :cols] = arr
    kind = "not square" if rows != cols else "not a power of two"
    note = (
        f"the {rows}x{cols} raster is {kind}: the quadtree was built on it padded with "
        f"zeros to {side}x{side} (the quads keep the raster's own coordinates)"
    )
    log.info("quadtree: %s", note)
    return out, note


def _unique_cells(values: np.ndarray, band: int | None) -> np.ndarray:
    """Fractional cells (strictly between 0 and 1), dilated by `band` cells."""
    if band is None:
        return np.zeros(values.shape, bool)
    unique = (values > 0) & (values < 1)
    for _ in range(band):
        unique = grown_by_one(unique)
    return unique


class _Emitter:
    """Collects quads (in cells of the current level) as pixel rectangles."""

    def __init__(self):
        self.parts: list[tuple[np.ndarray, ...]] = []

    def add(self, rows, cols, cell_px, h_cells, w_cells, sign, group):
        rows = np.asarray(rows)
        if rows.size == 0:
            return
        n = rows.size
        self.parts.append(
            (
                np.asarray(cols) * cell_px,
                rows * cell_px,
                np.full(n, w_cells * cell_px),
                np.full(n, h_cells * cell_px),
                np.full(n, float(sign)),
                np.asarray(group),
            )
        )

    def arrays(self) -> tuple[np.ndarray, ...]:
        if not self.parts:
            empty = np.zeros(0, np.int64)
            return empty, empty, empty, empty, np.zeros(0), empty
        return tuple(np.concatenate(c) for c in zip(*self.parts, strict=True))


def build_quadtree(raster, *, base_level: int = 0, band: int | None = 0) -> QuadLayout:
    """The quads of a raster (concrete values), by the paper's bottom-up quadtree.

    **Arguments:**

    - `raster`: 2-D real array (transmission). Not square or not a power of two: padded
      with zeros (see :attr:`QuadLayout.note`). All zero: refused (`InputDataError`).
    - `base_level`: 0 starts from pixels (exact); 1 from 2x2 means (the paper's half-size
      start, sec. 5.1); 2 from 4x4 means (its "aggressive" quarter size).
    - `band`: fractional cells and those within `band` cells of them are never merged
      (exact per-pixel gradients there); None merges by value alone (the paper's binary
      rasters have no fractional cells, so it makes no difference to them).

    **Returns:** a :class:`QuadLayout`.

    **Example:**

    ```python
    layout = build_quadtree(aperture.transmission(grid))
    layout.counts()   # {"quads": ..., "negative": ..., ...}
    ```
    """
    arr = _check_raster(raster)
    if isinstance(base_level, bool) or not isinstance(base_level, int) or base_level < 0:
        raise PhysicsRangeError(f"base_level must be an integer >= 0, got {base_level!r}")
    if band is not None and (isinstance(band, bool) or not isinstance(band, int) or band < 0):
        raise PhysicsRangeError(f"band must be None or an integer >= 0, got {band!r}")
    rows, cols = arr.shape
    padded, note = _padded(arr)
    side = padded.shape[0]
    if (1 << base_level) > side:
        raise PhysicsRangeError(
            f"base_level {base_level} starts from {1 << base_level}-pixel cells, larger than "
            f"the {side}-pixel raster"
        )
    cell = 1 << base_level
    m = side // cell
    values = padded.reshape(m, cell, m, cell).mean(axis=(1, 3))
    unique = _unique_cells(values, band)

    # Groups: each unique cell alone, then one per distinct non-zero value of the others.
    cell_group = np.full((m, m), -1, np.int64)
    n_unique = int(unique.sum())
    cell_group[unique] = np.arange(n_unique)
    shared = ~unique & (values != 0)
    distinct, inverse = np.unique(values[shared], return_inverse=True)
    cell_group[shared] = n_unique + inverse.reshape(-1)

    emit = _Emitter()
    r_u, c_u = np.nonzero(unique)
    emit.add(r_u, c_u, cell, 1, 1, +1, cell_group[r_u, c_u])

    # Per cell: uniform (mergeable) and its value's group (-1 for the value 0).
    uni = ~unique
    grp = np.where(uni, cell_group, -1)
    size = cell
    while uni.shape[0] > 1:
        if not np.any(uni & (grp >= 0)):
            break  # no uniform non-zero cell left: no level above can emit a quad
        uni, grp = _merge_level(uni, grp, size, emit)
        size *= 2
    if uni[0, 0] and grp[0, 0] >= 0:
        emit.add([0], [0], size, 1, 1, +1, [grp[0, 0]])

    x0, y0, w, h, sign, group = emit.arrays()
    group_cells = np.bincount(cell_group[cell_group >= 0], minlength=n_unique + distinct.size)
    order = np.lexsort((x0, y0, h, w))
    return QuadLayout(
        shape=(rows, cols),
        side=side,
        base_level=base_level,
        band=band,
        x0=x0[order].astype(np.int64),
        y0=y0[order].astype(np.int64),
        w=w[order].astype(np.int64),
        h=h[order].astype(np.int64),
        sign=sign[order],
        group=group[order].astype(np.int64),
        cell_group=cell_group.astype(np.int32),
        n_unique=n_unique,
        group_cells=group_cells.astype(np.int64),
        note=note,
    )


def _merge_level(
    uni: np.ndarray, grp: np.ndarray, size: int, emit: _Emitter
) -> tuple[np.ndarray, np.ndarray]:
    """One level up: emit what cannot merge, return the parents' (uniform, group)."""
    # Children of parent (i, j): a = (2i, 2j), b = (2i, 2j+1), c = (2i+1, 2j), d = (2i+1, 2j+1).
    u = [uni[0::2, 0::2], uni[0::2, 1::2], uni[1::2, 0::2], uni[1::2, 1::2]]
    g = [grp[0::2, 0::2], grp[0::2, 1::2], grp[1::2, 0::2], grp[1::2, 1::2]]
    offsets = [(0, 0), (0, 1), (1, 0), (1, 1)]
    pi, pj = np.indices(u[0].shape)

    def same(i, k):
        return u[i] & u[k] & (g[i] == g[k])

    all4 = same(0, 1) & same(0, 2) & same(0, 3)
    parent_uni = all4.copy()
    parent_grp = np.where(all4, g[0], -1)
    handled = all4.copy()

    # Three of four alike (non-zero): the parent takes their value, a negative quad the rest.
    for odd in range(4):
        rest = [k for k in range(4) if k != odd]
        three = same(rest[0], rest[1]) & same(rest[0], rest[2]) & (g[rest[0]] >= 0) & ~handled
        if not np.any(three):
            continue
        dy, dx = offsets[odd]
        rows, cols = 2 * pi[three] + dy, 2 * pj[three] + dx
        emit.add(rows, cols, size, 1, 1, -1, g[rest[0]][three])
        own = three & u[odd] & (g[odd] >= 0)
        emit.add(2 * pi[own] + dy, 2 * pj[own] + dx, size, 1, 1, +1, g[odd][own])
        parent_uni |= three
        parent_grp = np.where(three, g[rest[0]], parent_grp)
        handled |= three

    # The rest: mixed parents; emit the non-zero uniform children, adjacent pairs merged.
    todo = [~handled & u[k] & (g[k] >= 0) for k in range(4)]
    for first, second, vertical in ((0, 1, False), (2, 3, False), (0, 2, True), (1, 3, True)):
        pair = todo[first] & todo[second] & (g[first] == g[second])
        if np.any(pair):
            dy, dx = offsets[first]
            hc, wc = (2, 1) if vertical else (1, 2)
            emit.add(2 * pi[pair] + dy, 2 * pj[pair] + dx, size, hc, wc, +1, g[first][pair])
            todo[first] = todo[first] & ~pair
            todo[second] = todo[second] & ~pair
    for k in range(4):
        dy, dx = offsets[k]
        emit.add(2 * pi[todo[k]] + dy, 2 * pj[todo[k]] + dx, size, 1, 1, +1, g[k][todo[k]])
    return parent_uni, parent_grp
