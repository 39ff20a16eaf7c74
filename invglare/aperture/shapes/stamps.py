"""Local stamps: rasterising many small occluders at a cost independent of the image size.

A pupil can hold a thousand particles or grating lines, each only a few pixels
across. Evaluating every one of them on the full ``n x n`` grid would cost
``O(count * n**2)``; instead each element is evaluated on a small ``k x k``
window (a *stamp*) around the pixel nearest its anchor, and the stamps are
scatter-added into one image. The cost is ``O(count * k**2 + n**2)``: the ``k``
of an element depends on its size in pixels, not on `n`.

**Combining occluders.** Each element `i` has a coverage ``c_i`` (the analytic
soft coverage of :mod:`invglare.aperture.shapes.primitives`) and a weight ``w_i`` in
``[0, 1]`` (the relaxed-count weight). Occluders are independent, as in
:func:`invglare.aperture.occlude`: the transmission is ``prod(1 - w_i c_i)``.
The product is accumulated as a sum of logarithms, ``log(1 - w_i c_i)`` clamped
to at least ``log(eps)`` (`eps` the dtype's machine epsilon), because a
scatter-*add* is what JAX can do in parallel; one `exp` at the end gives the
transmission. Pixels covered completely by an element therefore transmit
``eps`` (about 1.2e-7 in float32), not 0.

**Differentiability.** The integer window origin (the anchor's nearest pixel)
is a `stop_gradient`; inside the window the coverage is the analytic one, a
smooth function of the element's position, size and weight, so gradients flow
as they do for full-image shapes. When an anchor crosses a pixel boundary the
window moves by one pixel, which changes nothing as long as the element fits in
the window either way (that is what :func:`window_half_px` guarantees).

**Window size.** Array shapes must be static, so the half-size ``h``
(``k = 2 h + 1``) is a Python integer: :func:`window_half_px` computes it from a
*concrete* bound on the element's half-extent (mm) and the grid pitch. Inside
`jit` those are traced; callers then fix ``h`` beforehand (see
:meth:`invglare.aperture.eye.EyeAperture.with_stamp_windows`). An element that
outgrows a fixed window is cut off at the window's edge.

Out-of-bounds pixels of a window (elements near or beyond the grid edge) are
dropped by the scatter.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from invglare._core.checks import is_concrete
from invglare._core.grids import ApertureGrid
from invglare._core.xla import materialise
from invglare.aperture.shapes.primitives import Capsule, Disk
from invglare.errors import ConfigError

#: Reach (px) of a window beyond the element's half-extent: 0.5 px for rounding the anchor
#: to its nearest pixel, plus up to ``(|nx| + |ny|) / 2 <= 0.71`` px over which a soft edge
#: still covers part of a pixel whose centre lies outside the shape.
WINDOW_MARGIN_PX = 1.25


def window_half_px(half_extent_mm: float | ArrayLike, pitch_mm: float | ArrayLike) -> int:
    """Half-size ``h`` (px) of a stamp window ``2 h + 1`` pixels wide holding an element.

    **Arguments:**

    - `half_extent_mm`: the largest distance (mm) from an element's anchor to a point of
      the element (a disk's radius; half a segment's length plus its half-thickness).
    - `pitch_mm`: the grid pitch (mm).

    Both must be concrete (not traced): a window size is a static array shape.

    **Returns:** ``ceil(half_extent / pitch + 1.25)``, at least 1.

    **Raises:** `ConfigError` when either value is traced.
    """
    if not (is_concrete(half_extent_mm) and is_concrete(pitch_mm)):
        raise ConfigError(
            "a stamp window size is a static array shape, so it needs concrete element "
            "sizes and grid pitch; inside jit / grad / vmap over them fix the window first "
            "(EyeAperture.with_stamp_windows(grid), or stamp_half_px / stamp_bound_mm on "
            "the component)"
        )
    ratio = float(half_extent_mm) / float(pitch_mm)
    if not math.isfinite(ratio) or ratio < 0.0:
        raise ConfigError(
            f"stamp half-extent {float(half_extent_mm):g} mm at pitch {float(pitch_mm):g} mm "
            "gives no finite window"
        )
    return max(1, math.ceil(ratio + WINDOW_MARGIN_PX))


def _window_origin(grid: ApertureGrid, anchors_mm: Array) -> tuple[Array, Array, Array]:
    """Nearest pixel (row, col) of each anchor and that pixel's centre (x, y) in mm.

    The integer position carries no gradient; the pixel centre depends on the pitch
    (differentiably) but not on the anchor.
    """
    pitch = grid.pitch_mm
    centre = grid.npix // 2
    idx = jax.lax.stop_gradient(jnp.round(anchors_mm / pitch))
    # Clamp before the integer cast: anchors far outside the grid (a vitreous particle
    # outside the pupil) must not overflow int32; their windows are dropped anyway.
    idx = jnp.clip(idx, -4 * grid.npix, 4 * grid.npix)
    col = idx[:, 0].astype(jnp.int32) + centre
    row = idx[:, 1].astype(jnp.int32) + centre
    return row, col, idx * pitch


@functools.partial(jax.jit, static_argnums=(3, 4))
def stamp_log_transmission(
    grid: ApertureGrid,
    anchors_mm: Float[ArrayLike, "n 2"],
    weights: Float[ArrayLike, " n"],
    half_px: int,
    coverage_fn: Callable[..., Array],
    *element_args: ArrayLike,
) -> Float[Array, "npix npix"]:
    """Sum over elements of ``log(1 - w_i c_i)``, each evaluated on its own small window.

    **Arguments:**

    - `grid`: the full grid.
    - `anchors_mm`: ``(n, 2)`` anchor points (x, y) in mm; each window is centred on the
      pixel nearest its anchor.
    - `weights`: ``(n,)`` element weights in ``[0, 1]`` (0 removes an element).
    - `half_px`: static window half-size (see :func:`window_half_px`).
    - `coverage_fn`: ``coverage_fn(local_grid, origin_mm, *args_i) -> (k, k)``: the
      coverage of element `i` on `local_grid` (a ``k x k`` grid of the same pitch whose
      centre pixel sits at `origin_mm` in the full grid's coordinates). Called under
      `vmap` over elements. It is a static argument of `jit`: pass a module-level
      function, not a fresh lambda, or every call compiles again.
    - `element_args`: per-element arrays, leading axis `n`, passed to `coverage_fn`.

    **Returns:** the ``(npix, npix)`` log-transmission (``<= 0``); add several of them and
    exponentiate once.
    """
    anchors = jnp.asarray(anchors_mm)
    weights = jnp.asarray(weights)
    dtype = jnp.result_type(grid.pitch_mm, weights, float)
    n = grid.npix
    k = 2 * int(half_px) + 1
    local = ApertureGrid(k, grid.pitch_mm)
    row, col, origin = _window_origin(grid, anchors)

    def one(origin_i, w_i, *args_i):
        c = coverage_fn(local, origin_i, *args_i)
        eps = jnp.finfo(dtype).eps
        return jnp.log(jnp.maximum(1.0 - w_i * c, eps)).astype(dtype)

    # Materialised: XLA would otherwise fuse the coverage into the scatter, which evaluates
    # it element by element, unvectorised (several times slower).
    logs = materialise(jax.vmap(one)(origin, weights, *element_args))
    offsets = jnp.arange(k) - int(half_px)
    rows = row[:, None] + offsets[None, :]
    cols = col[:, None] + offsets[None, :]
    # Negative indices would wrap around (numpy semantics) rather than be dropped.
    rows = jnp.where(rows < 0, n, rows)
    cols = jnp.where(cols < 0, n, cols)
    image = jnp.zeros((n, n), dtype=dtype)
    return image.at[rows[:, :, None], cols[:, None, :]].add(logs, mode="drop")


# Coverage functions of the stamped elements: module-level so that `jit` (with the function
# as a static argument) caches one compilation per kind of element.


def _disk_coverage(local: ApertureGrid, origin: Array, center: Array, radius: Array) -> Array:
    return Disk(2.0 * radius, center - origin).coverage(local)


def _capsule_coverage(
    local: ApertureGrid, origin: Array, start: Array, end: Array, thickness: Array
) -> Array:
    return Capsule(start - origin, end - origin, thickness).coverage(local)


def _mitred_segment_coverage(local, origin, a, b, t, p_lo, n_lo, lo, p_hi, n_hi, hi) -> Array:
    """A polyline segment's share: capsule `a`-`b` on the pixels between its mitre lines."""
    cov = Capsule(a - origin, b - origin, t).coverage(local)
    y, x = local.mesh_mm()
    x, y = x + origin[0], y + origin[1]
    after_lo = (x - p_lo[0]) * n_lo[0] + (y - p_lo[1]) * n_lo[1] >= 0.0
    before_hi = (x - p_hi[0]) * n_hi[0] + (y - p_hi[1]) * n_hi[1] < 0.0
    mine = jnp.where(lo, after_lo, True) & jnp.where(hi, before_hi, True)
    return jnp.where(mine, cov, 0.0)


def disks_log_transmission(
    grid: ApertureGrid,
    centers_mm: Float[ArrayLike, "n 2"],
    radii_mm: Float[ArrayLike, " n"],
    weights: Float[ArrayLike, " n"],
    half_px: int | None = None,
) -> Float[Array, "npix npix"]:
    """Log-transmission of `n` opaque soft disks (see :func:`stamp_log_transmission`).

    **Arguments:**

    - `centers_mm`: ``(n, 2)`` disk centres (x, y) in mm.
    - `radii_mm`: ``(n,)`` radii in mm (> 0).
    - `weights`: ``(n,)`` opacities / relaxed-count weights in ``[0, 1]``.
    - `half_px`: static window half-size; by default from the largest radius (which
      then must be concrete).

    Each disk's coverage is exactly :class:`invglare.aperture.Disk`'s full-image
    coverage, so ``exp`` of the result equals ``prod(1 - w_i * Disk_i.coverage(grid))``
    (up to the ``eps`` clamp) whenever every disk fits in its window.
    """
    centers = jnp.asarray(centers_mm)
    radii = jnp.asarray(radii_mm)
    if half_px is None:
        half_px = window_half_px(jnp.max(radii), grid.pitch_mm) if radii.size else 1

    return stamp_log_transmission(grid, centers, weights, half_px, _disk_coverage, centers, radii)


def segments_log_transmission(
    grid: ApertureGrid,
    starts_mm: Float[ArrayLike, "n 2"],
    ends_mm: Float[ArrayLike, "n 2"],
    thickness_mm: Float[ArrayLike, " n"],
    weights: Float[ArrayLike, " n"],
    half_px: int | None = None,
) -> Float[Array, "npix npix"]:
    """Log-transmission of `n` opaque capsules (segments with round ends).

    **Arguments:**

    - `starts_mm`, `ends_mm`: ``(n, 2)`` end points (x, y) in mm.
    - `thickness_mm`: ``(n,)`` widths in mm (> 0).
    - `weights`: ``(n,)`` opacities / relaxed-count weights in ``[0, 1]``.
    - `half_px`: static window half-size; by default from the largest
      ``length / 2 + thickness / 2`` (concrete).

    Windows are centred on the segments' midpoints; each coverage is exactly
    :class:`invglare.aperture.Capsule`'s.
    """
    starts = jnp.asarray(starts_mm)
    ends = jnp.asarray(ends_mm)
    thick = jnp.asarray(thickness_mm)
    mids = 0.5 * (starts + ends)
    if half_px is None:
        if thick.size:
            reach = 0.5 * jnp.linalg.norm(ends - starts, axis=-1) + 0.5 * thick
            half_px = window_half_px(jnp.max(reach), grid.pitch_mm)
        else:
            half_px = 1

    return stamp_log_transmission(
        grid, mids, weights, half_px, _capsule_coverage, starts, ends, thick
    )


def polyline_log_transmission(
    grid: ApertureGrid,
    points_mm: Float[ArrayLike, "m s+1 2"],
    thickness_mm: Float[ArrayLike, " m"],
    weights: Float[ArrayLike, " m"],
    half_px: int,
) -> Float[Array, "npix npix"]:
    """Log-transmission of `m` opaque thick polylines of `s` segments each (eyelashes).

    **Arguments:**

    - `points_mm`: ``(m, s + 1, 2)`` vertices (x, y) in mm of each polyline.
    - `thickness_mm`: ``(m,)`` width of each polyline (mm).
    - `weights`: ``(m,)`` opacity / relaxed-count weight of each polyline.
    - `half_px`: static window half-size; it must hold half a segment plus half a width
      stretched by ``1 + tan(bend / 2)`` (a mitred joint reaches past a segment's end
      on the outside of a bend); see :func:`window_half_px`.

    Each segment is stamped on its own window, so a long line costs its length times
    the window size, not the grid area. Adjacent segments overlap near their joint;
    to count each pixel once a segment only claims the pixels whose centres lie between
    the mitre lines of its two joints (the bisectors of the joint angles, where both
    segments are at the same distance), and there it covers them as a thick line
    running straight on through the joint (a mitred join). The two end segments keep
    their round caps at the polyline's ends. A straight polyline is therefore
    rasterised exactly like one :class:`~invglare.aperture.Capsule` from its first to
    its last vertex. At a bend, pixels straddling both an edge and a mitre line are
    off by a fraction of the bend angle: at 3 deg per joint, 9e-3 at most and 9e-4 on
    average over edge pixels, against the exact area of the round-joined outline.
    """
    pts = jnp.asarray(points_mm)
    m, s1, _ = pts.shape
    s = s1 - 1
    thick = jnp.asarray(thickness_mm)
    starts, ends = pts[:, :-1], pts[:, 1:]
    seg = ends - starts
    length = jnp.sqrt(jnp.maximum(jnp.sum(seg * seg, axis=-1, keepdims=True), 1e-30))
    u = seg / length  # (m, s, 2)
    # Mitre normals at the interior joints (between segment j - 1 and j), pointing forward.
    bis = u[:, :-1] + u[:, 1:]
    bis_len = jnp.sqrt(jnp.maximum(jnp.sum(bis * bis, axis=-1, keepdims=True), 1e-30))
    mitre = bis / bis_len  # (m, s - 1, 2)
    dtype = pts.dtype
    j = jnp.arange(s)
    has_lo = jnp.broadcast_to(j > 0, (m, s))
    has_hi = jnp.broadcast_to(j < s - 1, (m, s))
    pad = jnp.zeros((m, 1, 2), dtype)
    lo_normal = jnp.concatenate([pad, mitre], axis=1)
    hi_normal = jnp.concatenate([mitre, pad], axis=1)
    # Interior ends are pushed on by a segment and two widths, past the mitre lines (which lie
    # within about a width of the joint for bends up to 90 deg), so no round cap shows on the
    # pixels a segment claims; the mitre lines decide which segment covers a pixel. The push
    # does not depend on the window, so neither does the result.
    reach = length + 2.0 * thick[:, None, None] + 2.0 * grid.pitch_mm
    ext_starts = jnp.where(has_lo[..., None], starts - reach * u, starts)
    ext_ends = jnp.where(has_hi[..., None], ends + reach * u, ends)

    def flat(a):
        return a.reshape((m * s, *a.shape[2:]))

    per_segment = (
        flat(ext_starts),
        flat(ext_ends),
        jnp.repeat(thick, s),
        flat(starts),
        flat(lo_normal),
        flat(has_lo),
        flat(ends),
        flat(hi_normal),
        flat(has_hi),
    )
    mids = flat(0.5 * (starts + ends))
    w = jnp.repeat(jnp.asarray(weights), s)
    return stamp_log_transmission(grid, mids, w, half_px, _mitred_segment_coverage, *per_segment)


def transmission_from_log(log_t: Float[ArrayLike, "*shape"]) -> Float[Array, "*shape"]:
    """``exp(log_t)``: the transmission of accumulated stamps."""
    return jnp.exp(jnp.asarray(log_t))
