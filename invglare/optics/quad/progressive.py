"""Progressive refinement (sec. 4.3, fig. 3): an animated aperture's transform, frame by frame.

The transform is linear in the aperture, so frame ``t + 1``'s is frame ``t``'s plus the
transform of the difference ``D = a_{t+1} - a_t``. The difference is split into its
positive and negative parts (disoccluded and newly occluded light, the paper's two texture
channels), each gets its own quadtree, and only their quads are evaluated: a shadow moving
over an aperture changes a thin crescent, a blink the band the lid sweeps. A sparse
difference skips the quadtrees and is evaluated pixel by pixel (:func:`difference_quads`
says why).

What is carried from frame to frame are the four parity terms of
:mod:`~invglare.optics.quad.transform` (the complex transform on the output quadrant), far
or near field, in the working precision (60 frames of float32 updates of a shadow
crossing a heptagon stay within 1e-6 of the peak). Layouts differ every frame, so they are
evaluated as
:class:`~invglare.optics.quad.plan.DynamicPlan` arguments of one compiled function per
size bucket, not as constants of a program compiled per frame.

Everything here works on concrete rasters (numpy), frame after frame: it is the rendering
loop of an animation, outside `jit`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from invglare._core.checks import check_positive
from invglare._core.grids import AngularGrid, ApertureGrid
from invglare.errors import InputDataError
from invglare.optics.quad.farfield import far_field_from_terms
from invglare.optics.quad.nearfield import fresnel_kernel, near_field_from_terms
from invglare.optics.quad.options import check_representable, step_px
from invglare.optics.quad.plan import DynamicPlan, dynamic_plan, plan_arrays
from invglare.optics.quad.quadtree import build_quadtree
from invglare.optics.quad.transform import _terms, box_kernel, quadrant_index


def _convert(terms, power, step, npix: int, near: bool):
    convert = near_field_from_terms if near else far_field_from_terms
    return convert(terms, power, step, npix)


def _update(plan: DynamicPlan, amplitudes, step, alpha, npix: int, near: bool):
    index = quadrant_index(npix)
    kernel = fresnel_kernel if near else box_kernel
    params = alpha if near else None
    return _terms(plan, kernel, False, False, None, index, index, amplitudes, step, None, params)


@functools.partial(jax.jit, static_argnames=("npix", "near"))
def _advance(terms, plan, amplitudes, step, alpha, power, *, npix: int, near: bool):
    """The next frame: `terms` plus those of the quads of `plan` (None: from scratch)."""
    update = _update(plan, amplitudes, step, alpha, npix, near)
    new = update if terms is None else tuple(t + u for t, u in zip(terms, update, strict=True))
    return new, _convert(new, power, step, npix, near)


@functools.partial(jax.jit, static_argnames=("npix", "near"))
def _psf_only(terms, step, power, *, npix: int, near: bool):
    return _convert(terms, power, step, npix, near)


def _support(raster: np.ndarray) -> tuple[int, int, int, int] | None:
    """The bounding box (r0, r1, c0, c1) of a raster's non-zero values, or None."""
    rows = np.flatnonzero(np.any(raster != 0, axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(np.any(raster != 0, axis=0))
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def quads_of(
    raster: np.ndarray,
    base_level: int,
    sign: float = 1.0,
    origin: tuple[int, int] = (0, 0),
):
    """The quads of a raster's non-zero box (a difference is a thin crescent: its box is
    small) as pixel rectangles, placed at `origin` (row, column: where `raster`, a crop,
    sits in the whole raster), with their amplitudes (times `sign`).

    The box is widened to a square whose side is a power of two (zeros beyond the
    raster), the shape the quadtree takes without padding it again itself.
    """
    box = _support(raster)
    if box is None:
        return None
    r0, r1, c0, c1 = box
    cell = 1 << base_level
    r0 -= (r0 + origin[0]) % cell  # keep the cells on the whole raster's own grid
    c0 -= (c0 + origin[1]) % cell
    side = max(cell, 1 << math.ceil(math.log2(max(r1 - r0, c1 - c0))))
    crop = raster[r0 : r0 + side, c0 : c0 + side]
    if crop.shape != (side, side):
        crop = np.pad(crop, ((0, side - crop.shape[0]), (0, side - crop.shape[1])))
    layout = build_quadtree(crop, base_level=base_level, band=None)
    levels = layout.intensities_numpy(crop)
    amps = sign * levels[layout.group] * layout.sign
    return layout.x0 + c0 + origin[1], layout.y0 + r0 + origin[0], layout.w, layout.h, amps


#: A difference with at most this many non-zero pixels (a 256 x 256 crop) is evaluated
#: pixel by pixel, without quadtrees (at ``base_level`` 0): see :func:`difference_quads`.
PIXEL_QUADS_UP_TO = 65536


def difference_quads(crop: np.ndarray, base_level: int, origin: tuple[int, int]) -> list:
    """The quads of a difference crop placed at `origin` (row, column), as a list of parts.

    The paper's two channels, disoccluded (positive) and occluded (negative) light, each
    get their own quadtree. A difference of at most :data:`PIXEL_QUADS_UP_TO` non-zero
    pixels (a shadow's crescent) is instead one 1 x 1 quad per pixel, its amplitude the
    signed difference: building two quadtrees costs more than it saves there. The update's
    matrix products have the quads' distinct row intervals as their inner size: a crop's
    pixels have no more of those than the crop has rows and columns, where quads of many
    sizes have more (the benchmark's shadow on a 1024 px raster: 4 102 pixels in 128 row
    and 256 column intervals after padding, against 1 599 quadtree quads in 512), and so many
    pixels are summed into a dense matrix (:attr:`DynamicPlan.dense_inner
    <invglare.optics.quad.plan.DynamicPlan.dense_inner>`), not gathered one by one. A
    progressive frame of that shadow over the box, 2048 px output: 43 ms by quadtrees (gathered),
    20 ms by pixels (dense).
    """
    if base_level == 0:
        rows, cols = np.nonzero(crop)
        if rows.size <= PIXEL_QUADS_UP_TO:
            ones = np.ones(rows.size, np.int64)
            return [(cols + origin[1], rows + origin[0], ones, ones, crop[rows, cols])]
    return [
        quads_of(np.maximum(crop, 0.0), base_level, 1.0, origin),
        quads_of(np.maximum(-crop, 0.0), base_level, -1.0, origin),
    ]


def frame_plan(parts, shape: tuple[int, int]):
    """One padded plan (and amplitudes) of several quad lists, or None if all are empty."""
    parts = [p for p in parts if p is not None]
    if not parts:
        return None, None, 0
    x0, y0, w, h, amps = (np.concatenate(a) for a in zip(*parts, strict=True))
    arrays = plan_arrays(x0, y0, w, h, (shape[0] // 2, shape[1] // 2))
    dyn, padded = dynamic_plan(arrays, amps[arrays["order"]])
    # numpy arrays go to the compiled update as they are: jit converts them in C++, where
    # jnp.asarray would dispatch an eager conversion per array (about 0.1 ms each, a
    # good part of a small frame's update).
    return dyn, padded, int(amps.size)


@dataclasses.dataclass
class FrameStats:
    """What one frame cost: quads evaluated, seconds (quadtree + evaluation), full or not."""

    quads: int
    seconds: float
    full: bool


class ProgressiveQuads:
    """Frame-to-frame far or near field of an animated raster by difference quads.

    **Arguments:**

    - `grid`, `output`: the aperture raster's grid and the angular output grid.
    - `wavelength_nm`: the wavelength (one: spectral images are made from it by scaling).
    - `distance_mm`: None for the far field; a distance for the near field (eq. 4).
    - `base_level`: the quadtrees' base level (0 exact).
    - `refresh_every`: a full evaluation every this many frames (0: only the first).

    Call :meth:`psf` with each frame's raster in turn; :meth:`full_psf` evaluates a frame
    from scratch without touching the state (the reference the paper compares with).

    **Example:**

    ```python
    prog = ProgressiveQuads(grid, output, 550.0)
    psfs = [prog.psf(frame) for frame in frames]    # first full, then differences
    ```
    """

    def __init__(
        self,
        grid: ApertureGrid,
        output: AngularGrid,
        wavelength_nm: float,
        distance_mm: float | None = None,
        *,
        base_level: int = 0,
        refresh_every: int = 0,
    ):
        check_positive("wavelength_nm", wavelength_nm, "nm")
        if distance_mm is not None:
            check_positive("distance_mm", distance_mm, "mm")
        check_representable(grid, output, float(wavelength_nm), distance_mm)
        self.grid, self.output = grid, output
        self.near = distance_mm is not None
        self.step = float(step_px(grid, output, wavelength_nm))
        pitch = float(grid.pitch_mm)
        self.alpha = 0.0 if not self.near else pitch**2 / (wavelength_nm * 1e-6 * distance_mm)
        self.base_level = base_level
        self.refresh_every = int(refresh_every)
        self.dtype = jnp.result_type(float)
        self._terms = None
        self._raster = None
        self._frames = 0
        self.stats: list[FrameStats] = []

    def _check(self, raster) -> np.ndarray:
        arr = np.asarray(raster, dtype=np.float64)
        n = self.grid.npix
        if arr.shape != (n, n):
            raise InputDataError(f"a frame must be a {n}x{n} raster, got shape {arr.shape}")
        return arr

    def _evaluate(self, terms, parts, raster: np.ndarray):
        # Per unit power through the frame's aperture, its transmission sum |t| (the
        # normalisation of invglare.optics.fraunhofer). An empty frame (a closed blink) has
        # power 0 and an image of zeros.
        power = float(np.sum(np.abs(raster)))
        closed = power == 0.0  # start again from exact zeros
        plan, amps, quads = (None, None, 0) if closed else frame_plan(parts, raster.shape)
        if closed:
            terms = None
        step, alpha, power = (np.asarray(v, self.dtype) for v in (self.step, self.alpha, power))
        npix = self.output.npix
        if plan is None:
            if terms is None:
                side = npix // 2 + 1
                zero = jnp.zeros(
                    (side, side), jnp.result_type(self.dtype, 1j) if self.near else self.dtype
                )
                terms = (zero,) * 4
            return terms, _psf_only(terms, step, power, npix=npix, near=self.near), 0
        new, psf = _advance(
            terms, plan, np.asarray(amps, self.dtype), step, alpha, power,
            npix=npix, near=self.near,
        )  # fmt: skip
        return new, psf, quads

    def full_psf(self, raster) -> np.ndarray:
        """The frame's PSF evaluated from scratch (the state is left alone); its cost is in
        :attr:`last_full`."""
        arr = self._check(raster)
        start = time.perf_counter()
        _, psf, quads = self._evaluate(None, [quads_of(arr, self.base_level)], arr)
        psf = np.asarray(psf)
        self.last_full = FrameStats(quads, time.perf_counter() - start, True)
        return psf

    def psf(self, raster) -> np.ndarray:
        """The next frame's PSF: from scratch the first time (and at refreshes), else the
        previous frame's terms plus those of the difference quads."""
        arr = self._check(raster)
        start = time.perf_counter()
        refresh = self.refresh_every and self._frames % self.refresh_every == 0
        full = self._terms is None or bool(refresh)
        if full:
            parts = [quads_of(arr, self.base_level)]
            terms = None
        else:
            diff = arr - self._raster
            box = _support(diff)
            parts = []
            if box is not None:
                r0, r1, c0, c1 = box
                parts = difference_quads(diff[r0:r1, c0:c1], self.base_level, (r0, c0))
            terms = self._terms
        self._terms, psf, quads = self._evaluate(terms, parts, arr)
        psf = np.asarray(psf)
        self._raster = arr
        self._frames += 1
        self.stats.append(FrameStats(quads, time.perf_counter() - start, full))
        return psf


def moving_shadow(
    aperture: np.ndarray,
    radius_px: float,
    start_px: tuple[float, float],
    velocity_px: tuple[float, float],
) -> Callable[[int], np.ndarray]:
    """The paper's animation (sec. 5.1): a circular shadow over an aperture, moving by
    `velocity_px` (x, y) pixels per frame; returns ``frame(t) -> raster``. The shadow's
    edge is anti-aliased (a linear ramp one pixel wide across its radius)."""
    aperture = np.asarray(aperture, np.float64)
    n_rows, n_cols = aperture.shape
    reach = radius_px + 1.0  # the ramp reaches radius + 0.5

    def frame(t: int) -> np.ndarray:
        cx = start_px[0] + t * velocity_px[0]
        cy = start_px[1] + t * velocity_px[1]
        out = aperture.copy()
        # Only the pixels the shadow can reach change (the shadow is small; an n x n
        # pass per frame would cost more than the update it feeds).
        r0, r1 = max(0, math.floor(cy - reach)), min(n_rows, math.ceil(cy + reach) + 1)
        c0, c1 = max(0, math.floor(cx - reach)), min(n_cols, math.ceil(cx + reach) + 1)
        if r0 >= r1 or c0 >= c1:
            return out
        yy, xx = np.ogrid[r0:r1, c0:c1]
        r = np.hypot(xx - cx, yy - cy)
        out[r0:r1, c0:c1] *= 1.0 - np.clip(radius_px + 0.5 - r, 0.0, 1.0)
        return out

    return frame
