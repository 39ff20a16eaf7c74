"""Culling (sec. 4.3): skip the output tiles where the power spectrum is negligible.

A coarse pass evaluates the transform at the centre of every tile of the output quadrant
(1/8 of the resolution per axis for 8-pixel tiles, the paper's choice) together with its
*analytic* derivatives in ``f_x`` and ``f_y`` (autodiff of the closed form: the derivatives
of a quad's transform are closed forms too), for each of the four sign quadrants. A tile is
kept when the first-order bound on its amplitude,

    |F(c)| + 2 r (|dF/df_x(c)| + |dF/df_y(c)|),        r = half the tile in frequency,

reaches ``sqrt(threshold)`` of the peak amplitude: a tile across a zero of ``F`` (an Airy
ring) has a small value but not a small slope, and is kept. As the paper says, the test is
not strictly conservative (a feature narrower than a tile between samples can be missed);
:func:`culling_error` measures what it lost. The near field has no useful derivative bound
(the paper samples the function only): its tiles are kept where a sample reaches the
threshold, and so are their neighbours.

Like the quadtree, culling is decided on concrete values, once, for the wavelengths a
propagator will evaluate; the derivative of a culled transform is that of the whole one
(:func:`invglare.optics.quad.transform.parity_terms`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from invglare.optics.quad.plan import QuadPlan
from invglare.optics.quad.quadtree import grown_by_one
from invglare.optics.quad.transform import Kernel, Tiles, parity_terms, tile_runs

#: Default tile side (output pixels): one coarse sample per 8 x 8 pixels, as in the paper.
TILE = 8
#: Above this share of the quadrant evaluated (the kept tiles' bands and runs, gaps
#: bridged: :func:`~.transform.tile_runs`) the dense product is faster: no culling.
#: Measured at 1024 px on 2 cores: the heptagon (77 % evaluated) took 7.4 ms culled and
#: 6.4 ms dense, the box at 512 px (71 %) 0.93 and 0.88 ms; the box at 1024 (34 %) 2.9
#: and 3.8 ms; the heptagon at 2048 (38 %) 69 and 71 ms.
MAX_EVALUATED = 0.5

_SIGNS = ((1, 1), (1, -1), (-1, 1), (-1, -1))


def _combine(terms, far: bool, sx: int, sy: int):
    t1, t2, t3, t4 = terms
    if far:  # F = T1 - i sx T2 - i sy T3 - sx sy T4 (real terms)
        return jax.lax.complex(t1 - sx * sy * t4, -(sx * t2 + sy * t3))
    return t1 + sx * t2 + sy * t3 + (sx * sy) * t4


def tile_bounds(
    plan: QuadPlan,
    kernel: Kernel,
    amplitudes,
    step: float,
    npix: int,
    *,
    far: bool,
    params=None,
    tile: int = TILE,
) -> tuple[np.ndarray, float]:
    """Per tile of the quadrant, the largest amplitude bound over the four sign quadrants,
    and the peak amplitude (concrete values; see the module docstring)."""
    amps = jnp.asarray(amplitudes)
    dtype = amps.dtype
    n_tiles = -(-(npix // 2 + 1) // tile)
    centres = np.arange(n_tiles) * tile + tile // 2
    step_a = jnp.asarray(step, dtype)
    zero = jnp.zeros((), dtype)

    def at(off_y, off_x):
        return parity_terms(
            plan, kernel, amps, step_a, centres, centres, params, offsets=(off_y, off_x)
        )

    values, d_x = jax.jvp(lambda ox: at(zero, ox), (zero,), (jnp.ones((), dtype),))
    _, d_y = jax.jvp(lambda oy: at(oy, zero), (zero,), (jnp.ones((), dtype),))
    half = 0.5 * tile * step
    bound = 0.0
    for sy, sx in _SIGNS:
        amp = jnp.abs(_combine(values, far, sx, sy))
        if far:
            slope = jnp.abs(_combine(d_x, far, sx, sy)) + jnp.abs(_combine(d_y, far, sx, sy))
            amp = amp + 2.0 * half * slope
        bound = jnp.maximum(bound, amp)
    origin = parity_terms(plan, kernel, amps, step_a, np.zeros(1, int), np.zeros(1, int), params)
    peak = jnp.maximum(jnp.abs(_combine(origin, far, 1, 1))[0, 0], jnp.max(bound))
    return np.asarray(bound), float(peak)


def cull_tiles(
    plan: QuadPlan,
    kernel: Kernel,
    amplitudes,
    steps: tuple[float, ...],
    npix: int,
    threshold: float,
    *,
    far: bool,
    params: tuple = (None,),
    tile: int = TILE,
    max_evaluated: float = MAX_EVALUATED,
) -> Tiles | None:
    """The tiles of the quadrant to evaluate, for every (step, params) pair given.

    **Arguments:**

    - `amplitudes`: concrete quad amplitudes in the plan's order.
    - `steps`, `params`: the output pixel (cycles/px) and kernel parameters of each
      evaluation the tiles must serve (one per wavelength); a tile kept by any is kept.
    - `threshold`: relative to the peak *intensity*; 0 keeps everything.
    - `far`: the far-field bound (with derivatives), else the near field's.
    - `max_evaluated`: the largest share of the quadrant a culled evaluation may compute.

    **Returns:** the kept :class:`~invglare.optics.quad.transform.Tiles`, or None when
    they would make the culled evaluation compute more than `max_evaluated` of the
    quadrant, where the dense evaluation is faster.
    """
    if threshold <= 0:
        return None
    keep = None
    for step, par in zip(steps, params, strict=True):
        bound, peak = tile_bounds(
            plan, kernel, amplitudes, step, npix, far=far, params=par, tile=tile
        )
        mask = bound**2 >= threshold * peak**2
        # Neighbours of kept tiles are kept too: a margin for what the samples miss.
        mask = grown_by_one(mask)
        mask[0, 0] = True
        keep = mask if keep is None else keep | mask
    rows, cols = np.nonzero(keep)
    tiles = Tiles(tile, rows, cols)
    return tiles if evaluated_fraction(tiles, npix) <= max_evaluated else None


def culling_error(exact, culled) -> dict[str, float]:
    """What culling lost: the largest absolute error over the peak, and the energy share."""
    exact = np.asarray(exact, dtype=np.float64)
    culled = np.asarray(culled, dtype=np.float64)
    diff = np.abs(exact - culled)
    return {
        "max_error_over_peak": float(diff.max() / exact.max()),
        "lost_energy": float(np.sum(exact - culled) / np.sum(exact)),
    }


def evaluated_fraction(tiles: Tiles | None, npix: int) -> float:
    """Share of the quadrant a culled evaluation computes (1 without culling)."""
    if tiles is None:
        return 1.0
    side = npix // 2 + 1
    runs = tile_runs(tiles, (side, side))
    return float(sum((r1 - r0) * (c1 - c0) for r0, r1, c0, c1 in runs) / side**2)


def kept_fraction(tiles: Tiles | None, npix: int) -> float:
    """Share of the quadrant's tiles culling keeps (1 without culling); what the culled
    evaluation computes is their runs, :func:`evaluated_fraction`."""
    if tiles is None:
        return 1.0
    side = npix // 2 + 1
    n_tiles = -(-side // tiles.size)
    return float(tiles.rows.size / n_tiles**2)
