"""Exact area coverage of a square pixel by a half-plane.

Every soft shape in invglare is rasterised the same way: for each pixel, the
shape supplies the signed distance from the pixel centre to its boundary and the
boundary's outward unit normal there; the boundary is then treated as a straight
line (a half-plane) across the pixel, whose covered area has a closed form.
Straight edges are therefore exact; curved edges carry an error of about
``w**3 / (24 * R)`` px² per pixel (chord `w` px, radius of curvature `R` px), which
:func:`curved_edge_coverage` removes to first order in ``1 / R`` by subtracting the
sliver between the tangent line and the curve.

Why it works: if a point is drawn uniformly from a unit pixel, its offset from
the pixel centre projected on the normal ``(nx, ny)`` is ``nx*U + ny*V`` with
``U, V ~ Uniform(-1/2, 1/2)``; that is the sum of two uniforms of widths
``a = max(|nx|, |ny|)`` and ``b = min(|nx|, |ny|)``, whose density is a
trapezoid on ``[-(a+b)/2, (a+b)/2]``. The point is inside the half-plane when
its offset is below ``-sd``, so the covered fraction is the trapezoid's CDF at
``-sd``: quadratic, then linear, then quadratic.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero
from jaxtyping import Array, ArrayLike, Float

# A note on divisions: the rasterisers here run on every pixel of every stamp; on the CPU a
# division takes many times the cycles of a multiplication, and its derivative brings more
# divisions. So they share reciprocals: 1 / (pixel pitch) once per shape, 1 / a, 1 / nx,
# 1 / ny once per pixel. That took the daylight-eye fit's Jacobian from 57 to 35 ms (the
# tangent of the eyelash stamps is most of it).

#: Lower clamp of the trapezoid's short width `b`: keeps the quadratic pieces finite (and
#: their gradients free of NaN) for axis-aligned edges, where `b` is 0. Changes coverage by
#: at most ``b / 8 ~ 1e-7``.
_MIN_WIDTH = 1e-6


def _lower_tail(t: Array, a: Array, b: Array, inv_a: Array, inv_2ab: Array) -> Array:
    """Trapezoid CDF at ``t <= 0`` (the half below the median, where precision is best).

    Takes ``1 / a`` and ``1 / (2 a b)`` precomputed, so that the two edges of a strip
    share them (see the note on divisions above).
    """
    s = t + 0.5 * (a + b)  # distance from the left end of the support
    s_pos = jnp.maximum(s, 0.0)
    quad = s_pos * s_pos * inv_2ab
    # Written as (t + a/2) / a rather than (s - b/2) / a so that an axis-aligned edge
    # (a = 1) gives exactly 0.5 - sd.
    lin = (t + 0.5 * a) * inv_a
    return jnp.where(s <= 0.0, 0.0, jnp.where(s < b, quad, lin))


def edge_coverage(
    sd_px: Float[ArrayLike, "*shape"],
    nx: Float[ArrayLike, "*shape"],
    ny: Float[ArrayLike, "*shape"],
) -> Float[Array, "*shape"]:
    """Fraction of a unit square pixel lying inside a half-plane.

    **Arguments:**

    - `sd_px`: signed distance from the pixel centre to the half-plane's edge, in
      pixels; positive when the pixel centre is outside.
    - `nx`, `ny`: the edge's outward *unit* normal (x to the right, y up; the
      coverage only depends on `|nx|`, `|ny|`, so the convention of the y axis
      does not matter). Callers normalise it.

    All three broadcast against each other.

    **Returns:**

    The covered fraction in ``[0, 1]``: exactly ``clip(0.5 - sd_px, 0, 1)`` for an
    axis-aligned edge, 0 when ``sd_px >= (|nx| + |ny|) / 2`` and 1 when
    ``sd_px <= -(|nx| + |ny|) / 2``. It is continuously differentiable in `sd_px`
    and in the normal, and its gradients are finite everywhere.

    **Example:**

    ```python
    edge_coverage(0.25, 1.0, 0.0)  # 0.25: a vertical edge a quarter pixel left of the centre
    ```
    """
    a, b = _trapezoid_widths(nx, ny)
    return _coverage_from_widths(jnp.asarray(sd_px), a, b, *_width_reciprocals(a, b))


def strip_coverage(
    sd_near_px: Float[ArrayLike, "*shape"],
    sd_far_px: Float[ArrayLike, "*shape"],
    nx: Float[ArrayLike, "*shape"],
    ny: Float[ArrayLike, "*shape"],
) -> Float[Array, "*shape"]:
    """Fraction of a pixel between two parallel edges: ``edge_coverage(sd_near_px, nx, ny) -
    edge_coverage(sd_far_px, nx, ny)``, a strip such as a thick line (``sd_far_px >=
    sd_near_px``). The two edges share one normal, so they share its reciprocals."""
    a, b = _trapezoid_widths(nx, ny)
    inv_a, inv_2ab = _width_reciprocals(a, b)
    near = _coverage_from_widths(jnp.asarray(sd_near_px), a, b, inv_a, inv_2ab)
    return near - _coverage_from_widths(jnp.asarray(sd_far_px), a, b, inv_a, inv_2ab)


def _trapezoid_widths(nx: ArrayLike, ny: ArrayLike) -> tuple[Array, Array]:
    """``(max(|nx|, |ny|), min(|nx|, |ny|))``, both clamped below by `_MIN_WIDTH`."""
    ax = jnp.abs(jnp.asarray(nx))
    ay = jnp.abs(jnp.asarray(ny))
    a = jnp.maximum(jnp.maximum(ax, ay), _MIN_WIDTH)
    b = jnp.maximum(jnp.minimum(ax, ay), _MIN_WIDTH)
    return a, b


def _coverage_from_widths(sd_px: Array, a: Array, b: Array, inv_a: Array, inv_2ab: Array) -> Array:
    """`edge_coverage` for the trapezoid widths `a` >= `b` of the normal and their
    reciprocals ``1 / a``, ``1 / (2 a b)`` (from `_width_reciprocals`)."""
    x = -sd_px
    # Evaluate the lower half only and mirror it (CDF(x) = 1 - CDF(-x)); the branch is
    # chosen with `where` rather than `abs` so that the derivative at x = 0 is the density.
    below = x <= 0.0
    t = jnp.where(below, x, -x)
    tail = _lower_tail(t, a, b, inv_a, inv_2ab)
    return jnp.where(below, tail, 1.0 - tail)


def _width_reciprocals(a: Array, b: Array) -> tuple[Array, Array]:
    inv_a = 1.0 / a
    return inv_a, 0.5 * inv_a / b


def tangent_chord(
    sd_px: Float[ArrayLike, "*shape"],
    nx: Float[ArrayLike, "*shape"],
    ny: Float[ArrayLike, "*shape"],
) -> tuple[Float[Array, "*shape"], Float[Array, "*shape"]]:
    """Where the edge line crosses the pixel, as an interval of tangent coordinate (px).

    The edge line is ``q(t) = -sd_px * n + t * (-ny, nx)`` in coordinates centred on the
    pixel (``t = 0`` is the foot of the perpendicular from the pixel centre). Returns
    ``(t_lo, t_hi)``, clipped to ``[-1, 1]`` and with ``t_hi == t_lo`` when the line
    misses the pixel.
    """
    sd_px = jnp.asarray(sd_px)
    nx = jnp.asarray(nx)
    ny = jnp.asarray(ny)
    # Each of |qx| <= 1/2 and |qy| <= 1/2 confines t to an interval (to all t when the
    # normal lies along that axis: the clamp turns that into a huge interval and leaves the
    # other constraint to decide).
    inv_nx = 1.0 / jnp.where(jnp.abs(nx) > _MIN_WIDTH, nx, _MIN_WIDTH)
    inv_ny = 1.0 / jnp.where(jnp.abs(ny) > _MIN_WIDTH, ny, _MIN_WIDTH)
    c1, h1 = -sd_px * nx * inv_ny, 0.5 * jnp.abs(inv_ny)
    c2, h2 = sd_px * ny * inv_nx, 0.5 * jnp.abs(inv_nx)
    # A chord inside the pixel has |t| <= sqrt(2)/2; clipping to [-1, 1] keeps later powers
    # of t finite however large the clamped intervals are.
    t_lo = jnp.clip(jnp.maximum(c1 - h1, c2 - h2), -1.0, 1.0)
    t_hi = jnp.clip(jnp.minimum(c1 + h1, c2 + h2), t_lo, 1.0)
    return t_lo, t_hi


def sliver_integral(
    t_lo: ArrayLike,
    t_hi: ArrayLike,
    t0: ArrayLike = 0.0,
    t1: ArrayLike = -2.0,
    t2: ArrayLike = 2.0,
) -> Array:
    """``integral of D(t) dt`` over ``[t_lo, t_hi]`` for a unit-curvature deviation profile.

    ``D(t) = ((t - t0)**2 - (t1 - t)_+**2 - (t - t2)_+**2) / 2``: a parabola with vertex
    `t0` between `t1 <= t0 <= t2` and its tangent lines outside, i.e. how far an edge
    of curvature 1 (between tangent coordinates `t1` and `t2`, straight beyond them)
    departs inwards from the tangent line at `t0`. Multiply by the curvature.
    The defaults (``t1 = -2``, ``t2 = 2``) leave the parabola whole across any chord.
    """
    t_lo, t_hi = jnp.asarray(t_lo), jnp.asarray(t_hi)
    # Integrated piece by piece rather than through one antiderivative: that would take
    # differences of cubes of |t - t0|, which can be tens of pixels (a capsule side's arc
    # starts far along the side) and would lose all float32 precision.
    a, b = jnp.clip(t_lo, t1, t2), jnp.clip(t_hi, t1, t2)
    parabola = ((b - t0) ** 3 - (a - t0) ** 3) * (1.0 / 6.0)

    def tangent_piece(lo, hi, tk):
        # integral over [lo, hi] of the tangent line at tk: (tk - t0) * (t - (tk + t0) / 2)
        return (tk - t0) * (hi - lo) * (0.5 * (lo + hi) - 0.5 * (tk + t0))

    left = tangent_piece(jnp.minimum(t_lo, t1), jnp.minimum(t_hi, t1), t1)
    right = tangent_piece(jnp.maximum(t_lo, t2), jnp.maximum(t_hi, t2), t2)
    return parabola + left + right


def curved_edge_coverage(
    sd_px: Float[ArrayLike, "*shape"],
    nx: Float[ArrayLike, "*shape"],
    ny: Float[ArrayLike, "*shape"],
    curvature_per_px: Float[ArrayLike, "*shape"],
) -> Float[Array, "*shape"]:
    """Pixel coverage by a shape whose edge is curved, to first order in the curvature.

    The half-plane coverage of :func:`edge_coverage` counts the sliver between the
    edge's tangent line (at the point nearest the pixel centre) and the curved edge.
    That sliver is ``kappa * t**2 / 2`` thick at distance `t` along the tangent, so
    its area inside the pixel is ``kappa / 2 * integral(t**2 dt)`` over the tangent's
    chord through the pixel, ``kappa / 6 * (t_hi**3 - t_lo**3)``; it is subtracted.
    This removes the ``~ w**3 / (24 R)`` px² error per boundary pixel of the plain
    half-plane rule, leaving an error of second order in ``1 / R``.

    **Arguments:**

    - `sd_px`, `nx`, `ny`: as for :func:`edge_coverage`.
    - `curvature_per_px`: curvature of the edge at its point nearest the pixel centre,
      in 1/px (1 / radius of curvature); positive where the shape is convex there.

    **Returns:**

    The covered fraction, clipped to ``[0, 1]``. Meant for radii of curvature of a
    pixel or more; below that no local approximation is accurate.

    Its derivatives are written out (:func:`_curved_edge_jvp`) rather than traced:
    autodiff of the piecewise formula made XLA's CPU backend write some forty
    intermediate arrays per pixel grid, and a disk raster's gradient took five times
    its forward pass.
    """
    return _curved_edge(
        jnp.asarray(sd_px), jnp.asarray(nx), jnp.asarray(ny), jnp.asarray(curvature_per_px)
    )


@jax.custom_jvp
def _curved_edge(sd_px: Array, nx: Array, ny: Array, curvature_per_px: Array) -> Array:
    a, b = _trapezoid_widths(nx, ny)
    return jnp.clip(_curved_edge_raw(sd_px, a, b, curvature_per_px)[0], 0.0, 1.0)


def _curved_edge_raw(sd_px: Array, a: Array, b: Array, kappa: Array) -> tuple[Array, ...]:
    """``(flat - kappa / 6 * cubes, t_lo, t_hi, cubes)``: the unclipped coverage, the
    tangent's chord through the pixel and ``cubes = t_hi**3 - t_lo**3``."""
    flat = _coverage_from_widths(sd_px, a, b, *_width_reciprocals(a, b))
    # The square pixel is symmetric under reflections and the swap of x and y, so the
    # chord is that of the normal (a, b) up to t -> -t, which leaves the integral of t**2
    # unchanged. The chord lies in [-1, 1], where the sliver profile is the plain
    # parabola of `sliver_integral`.
    t_lo, t_hi = tangent_chord(sd_px, a, b)
    cubes = t_hi**3 - t_lo**3
    return flat - kappa * (1.0 / 6.0) * cubes, t_lo, t_hi, cubes


def _curved_edge_jvp(primals, tangents):
    """``d coverage = P_sd dsd + P_a da + P_b db + P_kappa dkappa`` with the partials
    of the trapezoid CDF and of the chord ends written out; `a`, `b` follow `nx`, `ny`
    through the larger and the smaller of their magnitudes."""
    sd, nx, ny, kappa = primals
    dsd, dnx, dny, dkappa = tangents
    normal_moves = not (_is_zero(dnx) and _is_zero(dny))
    a, b = _trapezoid_widths(nx, ny)
    inv_a, inv_2ab = _width_reciprocals(a, b)

    raw, t_lo, t_hi, cubes = _curved_edge_raw(sd, a, b, kappa)
    coverage = jnp.clip(raw, 0.0, 1.0)
    live = (raw > 0.0) & (raw < 1.0)
    lo_branch, hi_branch = _chord_branches(sd, a, b, t_lo)

    # The flat part is CDF(-sd) of the trapezoid, through its lower tail L(t), t = -|sd|:
    # 0, then s^2 / (2ab) (s = t + (a + b) / 2 < b), then (t + a / 2) / a.
    below = sd >= 0.0
    t = jnp.where(below, -sd, sd)
    s = t + 0.5 * (a + b)
    in_quad = (s > 0.0) & (s < b)
    in_lin = s >= b
    density = jnp.where(in_lin, inv_a, jnp.where(in_quad, 2.0 * s * inv_2ab, 0.0))

    # Chord ends: each is one of two lines in sd (or clipped, or the other end).
    inv_b = 1.0 / b
    lo_free = jnp.abs(t_lo) < 1.0
    hi_is_lo = hi_branch == 2
    hi_free = (jnp.abs(t_hi) < 1.0) & ~hi_is_lo
    lo_first = lo_branch == 0
    hi_first = hi_branch == 0
    d_lo_sd = jnp.where(lo_free, jnp.where(lo_first, -a * inv_b, b * inv_a), 0.0)
    d_hi_sd = jnp.where(
        hi_is_lo, d_lo_sd, jnp.where(hi_free, jnp.where(hi_first, -a * inv_b, b * inv_a), 0.0)
    )
    w_lo = 0.5 * kappa * t_lo * t_lo
    w_hi = 0.5 * kappa * t_hi * t_hi
    # d raw = d flat - kappa * (t_hi^2 d t_hi - t_lo^2 d t_lo) / 2 - cubes / 6 d kappa
    # The partials are masked where the clip holds, before they meet the tangents: reverse
    # mode then keeps one array per partial and no mask.
    p_sd = jnp.where(live, -density - w_hi * d_hi_sd + w_lo * d_lo_sd, 0.0)
    out = _times(p_sd, dsd) + _times(jnp.where(live, cubes * (-1.0 / 6.0), 0.0), dkappa)
    if normal_moves:
        # d flat / d(a, b): the tail's derivative, sign-flipped in the upper half.
        sign = jnp.where(below, 1.0, -1.0)
        quad = s * s * inv_2ab
        q_a = jnp.where(
            in_lin, -t * inv_a * inv_a, jnp.where(in_quad, s * inv_2ab - quad * inv_a, 0.0)
        )
        q_b = jnp.where(in_quad, s * inv_2ab - quad * inv_b, 0.0)
        # chord ends: c1 -/+ h1 = -sd a / b -/+ 1 / (2b), c2 -/+ h2 = sd b / a -/+ 1 / (2a)
        inv_a2 = inv_a * inv_a
        inv_b2 = inv_b * inv_b
        first_a, first_b = -sd * inv_b, sd * a * inv_b2
        second_a, second_b = -sd * b * inv_a2, sd * inv_a
        d_lo_a = jnp.where(lo_free, jnp.where(lo_first, first_a, second_a + 0.5 * inv_a2), 0.0)
        d_lo_b = jnp.where(lo_free, jnp.where(lo_first, first_b + 0.5 * inv_b2, second_b), 0.0)
        d_hi_a = jnp.where(hi_free, jnp.where(hi_first, first_a, second_a - 0.5 * inv_a2), 0.0)
        d_hi_b = jnp.where(hi_free, jnp.where(hi_first, first_b - 0.5 * inv_b2, second_b), 0.0)
        d_hi_a = jnp.where(hi_is_lo, d_lo_a, d_hi_a)
        d_hi_b = jnp.where(hi_is_lo, d_lo_b, d_hi_b)
        p_a = jnp.where(live, sign * q_a - w_hi * d_hi_a + w_lo * d_lo_a, 0.0)
        p_b = jnp.where(live, sign * q_b - w_hi * d_hi_b + w_lo * d_lo_b, 0.0)
        da, db = _width_tangents(nx, ny, dnx, dny)
        out = out + p_a * da + p_b * db
    return coverage, out


_curved_edge.defjvp(_curved_edge_jvp, symbolic_zeros=True)


def _chord_branches(sd: Array, a: Array, b: Array, t_lo: Array) -> tuple[Array, Array]:
    """Which bound set each end of `tangent_chord(sd, a, b)`: 0 for the pair of lines
    ``|qy| <= 1/2`` (``c1 -/+ h1``), 1 for ``|qx| <= 1/2``, and for the upper end 2 when
    it is pinned to the lower one (the line misses the pixel)."""
    inv_b, inv_a = 1.0 / b, 1.0 / a
    c1, h1 = -sd * a * inv_b, 0.5 * inv_b
    c2, h2 = sd * b * inv_a, 0.5 * inv_a
    lo_branch = jnp.where(c1 - h1 >= c2 - h2, 0, 1)
    hi_raw = jnp.minimum(c1 + h1, c2 + h2)
    hi_branch = jnp.where(hi_raw <= t_lo, 2, jnp.where(c1 + h1 <= c2 + h2, 0, 1))
    return lo_branch, hi_branch


def _width_tangents(nx: Array, ny: Array, dnx, dny) -> tuple[Array, Array]:
    """Tangents of ``a = max(|nx|, |ny|)`` and ``b = min(|nx|, |ny|)`` (zero where clamped)."""
    ax, ay = jnp.abs(nx), jnp.abs(ny)
    ex = _times(jnp.sign(nx), dnx)
    ey = _times(jnp.sign(ny), dny)
    x_is_a = ax >= ay
    da = jnp.where(jnp.maximum(ax, ay) > _MIN_WIDTH, jnp.where(x_is_a, ex, ey), 0.0)
    db = jnp.where(jnp.minimum(ax, ay) > _MIN_WIDTH, jnp.where(x_is_a, ey, ex), 0.0)
    return da, db


def _is_zero(tangent) -> bool:
    return isinstance(tangent, SymbolicZero)


def _times(partial_: Array, tangent) -> Array:
    """``partial * tangent``, or 0 for a symbolic zero tangent."""
    return jnp.zeros_like(partial_) if _is_zero(tangent) else partial_ * tangent
