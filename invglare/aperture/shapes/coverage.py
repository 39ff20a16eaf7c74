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
    """``d coverage = P_sd dsd + P_a da + P_b db + P_kappa dkappa`` with the partials of
    the trapezoid CDF and of the chord ends written out; `a`, `b` follow `nx`, `ny`
    through the larger and the smaller of their magnitudes."""
    sd, nx, ny, kappa = primals
    dsd, dnx, dny, dkappa = tangents
    a, b = _trapezoid_widths(nx, ny)
    inv_a, inv_2ab = _width_reciprocals(a, b)
    raw, t_lo, t_hi, cubes = _curved_edge_raw(sd, a, b, kappa)
    # The partials are masked where the clip holds, before they meet the tangents: reverse
    # mode then keeps one array per partial and no mask.
    live = (raw > 0.0) & (raw < 1.0)
    density, e_a, e_b = _flat_partials(sd, a, b, inv_a, inv_2ab)
    # The chord of the normal (a, b) (see `_curved_edge_raw`).
    lo_sd, hi_sd, lo_a, hi_a, lo_b, hi_b = _chord_partials(sd, a, b, t_lo, t_hi)
    # d raw = d flat - kappa * (t_hi^2 d t_hi - t_lo^2 d t_lo) / 2 - cubes / 6 d kappa
    w_lo = 0.5 * kappa * t_lo * t_lo
    w_hi = 0.5 * kappa * t_hi * t_hi
    p_sd = jnp.where(live, -density - w_hi * hi_sd + w_lo * lo_sd, 0.0)
    out = _times(p_sd, dsd) + _times(jnp.where(live, cubes * (-1.0 / 6.0), 0.0), dkappa)
    if not (_is_zero(dnx) and _is_zero(dny)):
        p_a = jnp.where(live, e_a - w_hi * hi_a + w_lo * lo_a, 0.0)
        p_b = jnp.where(live, e_b - w_hi * hi_b + w_lo * lo_b, 0.0)
        p_nx, p_ny = _width_adjoints(nx, ny, p_a, p_b)
        out = out + _times(p_nx, dnx) + _times(p_ny, dny)
    return jnp.clip(raw, 0.0, 1.0), out


_curved_edge.defjvp(_curved_edge_jvp, symbolic_zeros=True)


def _flat_partials(
    sd: Array, a: Array, b: Array, inv_a: Array, inv_2ab: Array
) -> tuple[Array, Array, Array]:
    """``(density, dE/da, dE/db)`` of the flat coverage ``E = CDF(-sd)`` of the trapezoid
    (``dE/dsd = -density``), through its lower tail ``L(t)``, ``t = -|sd|``: 0, then
    ``s^2 / (2ab)`` (``s = t + (a + b) / 2 < b``), then ``(t + a / 2) / a``; the upper half
    is ``1 - L``, so its width derivatives change sign."""
    below = sd >= 0.0
    t = jnp.where(below, -sd, sd)
    s = t + 0.5 * (a + b)
    in_quad = (s > 0.0) & (s < b)
    in_lin = s >= b
    density = jnp.where(in_lin, inv_a, jnp.where(in_quad, 2.0 * s * inv_2ab, 0.0))
    quad = s * s * inv_2ab
    slope = s * inv_2ab
    q_a = jnp.where(in_lin, -t * inv_a * inv_a, jnp.where(in_quad, slope - quad * inv_a, 0.0))
    q_b = jnp.where(in_quad, slope - quad / b, 0.0)
    sign = jnp.where(below, 1.0, -1.0)
    return density, sign * q_a, sign * q_b


def _chord_partials(
    sd: Array, nx: Array, ny: Array, t_lo: Array, t_hi: Array
) -> tuple[Array, Array, Array, Array, Array, Array]:
    """Partials of the ends of ``tangent_chord(sd, nx, ny)`` (given as `t_lo`, `t_hi`):
    ``(lo_sd, hi_sd, lo_nx, hi_nx, lo_ny, hi_ny)``.

    Each end is one of the lines ``c1 -/+ h1 = (-sd nx -/+ 1/2) / ny`` (the bounds
    ``|qy| <= 1/2``) or ``c2 -/+ h2 = (sd ny -/+ 1/2) / nx`` (``|qx| <= 1/2``; signs of the
    halves as for positive nx, ny), whichever binds, or clipped to +/-1 (then constant);
    the upper end may be pinned to the lower one (the line misses the pixel). The clamped
    reciprocals of `tangent_chord` are constant where they clamp.
    """
    fx = jnp.abs(nx) > _MIN_WIDTH
    fy = jnp.abs(ny) > _MIN_WIDTH
    ix = 1.0 / jnp.where(fx, nx, _MIN_WIDTH)
    iy = 1.0 / jnp.where(fy, ny, _MIN_WIDTH)
    c1, h1 = -sd * nx * iy, 0.5 * jnp.abs(iy)
    c2, h2 = sd * ny * ix, 0.5 * jnp.abs(ix)
    lo_first = c1 - h1 >= c2 - h2
    hi_first = c1 + h1 <= c2 + h2
    lo_free = jnp.abs(t_lo) < 1.0
    pinned = jnp.minimum(c1 + h1, c2 + h2) <= t_lo
    hi_free = (jnp.abs(t_hi) < 1.0) & ~pinned

    def ends(first, second, half_first, half_second):
        """(lo, hi) partials from those of c1, c2 and of h1, h2."""
        lo = jnp.where(lo_free, jnp.where(lo_first, first - half_first, second - half_second), 0.0)
        hi = jnp.where(hi_free, jnp.where(hi_first, first + half_first, second + half_second), 0.0)
        return lo, jnp.where(pinned, lo, hi)

    gx = jnp.where(fx, ix * ix, 0.0)  # -d(1/nx)/dnx where 1/nx is not clamped
    gy = jnp.where(fy, iy * iy, 0.0)
    zero = jnp.zeros_like(c1)
    lo_sd, hi_sd = ends(-nx * iy, ny * ix, zero, zero)
    lo_nx, hi_nx = ends(-sd * iy, -sd * ny * gx, zero, -0.5 * jnp.sign(nx) * gx)
    lo_ny, hi_ny = ends(sd * nx * gy, sd * ix, -0.5 * jnp.sign(ny) * gy, zero)
    return lo_sd, hi_sd, lo_nx, hi_nx, lo_ny, hi_ny


def _is_zero(tangent) -> bool:
    return isinstance(tangent, SymbolicZero)


def _times(partial_: Array, tangent) -> Array:
    """``partial * tangent``, or 0 for a symbolic zero tangent."""
    return jnp.zeros_like(partial_) if _is_zero(tangent) else partial_ * tangent


def capsule_edge_coverage(
    sd_px: Array,
    far_px: Array,
    nx: Array,
    ny: Array,
    r_px: Array,
    t_px: Array,
    len_px: Array,
    t_near: Array,
    side_sign: Array,
    at_end: Array,
) -> Array:
    """Pixel coverage by a capsule (a segment thickened to radius `r_px`), given per pixel
    its local edge: `sd_px` and `far_px` are the signed distances to the near and far
    side (px), ``(nx, ny)`` the outward normal, `t_px` the position along the axis from
    the start, `len_px` the axis length, `side_sign` (+1 / -1) the side of the axis,
    `at_end` whether the nearest point is on a round end, and `t_near` the tangent
    coordinate of the junction of that end with the side (see
    :meth:`invglare.aperture.Capsule.coverage`, which computes them).

    The coverage is the strip between the two sides (:func:`strip_coverage`) less the
    sliver between the local tangent line and the round ends (:func:`sliver_integral`),
    clipped to ``[0, 1]``. Its derivatives are written out, as for
    :func:`curved_edge_coverage`: traced, the gradient of the night eye's raster (lashes
    and gratings are capsules) took 37 times its forward pass at 128², written out 15
    times (`invglare bench`, case `eye_raster_grad`).
    """
    return _capsule(sd_px, far_px, nx, ny, r_px, t_px, len_px, t_near, side_sign, at_end)


def _capsule_raw(sd, far, nx, ny, r, tp, lp, tn, sign, at_end):
    """Unclipped coverage, and the pieces `_capsule_jvp` reuses."""
    strip = strip_coverage(sd, far, nx, ny)
    t_lo, t_hi = tangent_chord(sd, nx, ny)
    # End pixels: the tangent point is the vertex; the near junction lies at r sin(beta)
    # (beta = angle from the side), the far one is bounded at r (the arc's quarter).
    t_far = jnp.where(tn >= 0.0, -r, r)
    end_args = (t_lo, t_hi, 0.0, jnp.minimum(tn, t_far), jnp.maximum(tn, t_far))
    # Side pixels: the tangent line is the side itself; along it, the start's arc begins
    # at tangent coordinate sign * t (towards +sign) and the end's at sign * (t - L)
    # (towards -sign); mirror the chord so that each arc lies towards +t.
    lo_a = jnp.minimum(sign * t_lo, sign * t_hi)
    hi_a = jnp.maximum(sign * t_lo, sign * t_hi)
    to_end = lp - tp
    start_args = (lo_a, hi_a, tp, tp, tp + r)
    end_side_args = (-hi_a, -lo_a, to_end, to_end, to_end + r)
    side = sliver_integral(*start_args) + sliver_integral(*end_side_args)
    # (the floor only matters for a zero thickness reached inside a traced fit)
    inv_r = 1.0 / jnp.maximum(r, 1e-6)
    sliver_over_r = jnp.where(at_end, sliver_integral(*end_args), side)
    raw = strip - sliver_over_r * inv_r
    return raw, (t_lo, t_hi, t_far, end_args, start_args, end_side_args, inv_r, sliver_over_r)


@jax.custom_jvp
def _capsule(sd, far, nx, ny, r, tp, lp, tn, sign, at_end):
    return jnp.clip(_capsule_raw(sd, far, nx, ny, r, tp, lp, tn, sign, at_end)[0], 0.0, 1.0)


def _capsule_jvp(primals, tangents):
    """The coverage's partials in each differentiable input, by a hand-written backward
    pass of a unit cotangent through the (elementwise) formula; then ``sum P_i d_i``."""
    sd, far, nx, ny, r, _, _, tn, sign, at_end = primals
    raw, pieces = _capsule_raw(*primals)
    t_lo, t_hi, t_far, end_args, start_args, end_side_args, inv_r, sliver_over_r = pieces
    live = (raw > 0.0) & (raw < 1.0)
    g_sliver = jnp.where(live, -inv_r, 0.0)  # d raw / d sliver_over_r
    g_r = jnp.where(live & (r > 1e-6), sliver_over_r * inv_r * inv_r, 0.0)
    g_end = jnp.where(at_end, g_sliver, 0.0)
    g_side = jnp.where(at_end, 0.0, g_sliver)

    # the end pixels' sliver
    e_lo, e_hi, _, e_1, e_2 = _sliver_partials(*end_args)
    g_tlo, g_thi = g_end * e_lo, g_end * e_hi
    near_first = tn <= t_far
    g_e1, g_e2 = g_end * e_1, g_end * e_2
    g_tn = jnp.where(near_first, g_e1, g_e2)
    g_tfar = jnp.where(near_first, g_e2, g_e1)
    g_r = g_r + jnp.where(tn >= 0.0, -g_tfar, g_tfar)
    # the side pixels' two slivers (start arc, end arc)
    s_lo, s_hi, s_0, s_1, s_2 = _sliver_partials(*start_args)
    q_lo, q_hi, q_0, q_1, q_2 = _sliver_partials(*end_side_args)
    g_lo_a = g_side * (s_lo - q_hi)
    g_hi_a = g_side * (s_hi - q_lo)
    g_to_end = g_side * (q_0 + q_1 + q_2)
    g_tp = g_side * (s_0 + s_1 + s_2) - g_to_end
    g_lp = g_to_end
    g_r = g_r + g_side * (s_2 + q_2)
    up = sign > 0.0
    g_tlo = g_tlo + jnp.where(up, g_lo_a, -g_hi_a)
    g_thi = g_thi + jnp.where(up, g_hi_a, -g_lo_a)
    # the chord, then the strip
    lo_sd, hi_sd, lo_nx, hi_nx, lo_ny, hi_ny = _chord_partials(sd, nx, ny, t_lo, t_hi)
    a, b = _trapezoid_widths(nx, ny)
    inv_a, inv_2ab = _width_reciprocals(a, b)
    near_density, near_a, near_b = _flat_partials(sd, a, b, inv_a, inv_2ab)
    far_density, far_a, far_b = _flat_partials(far, a, b, inv_a, inv_2ab)
    g_sd = jnp.where(live, -near_density, 0.0) + g_tlo * lo_sd + g_thi * hi_sd
    g_far = jnp.where(live, far_density, 0.0)
    g_a = jnp.where(live, near_a - far_a, 0.0)
    g_b = jnp.where(live, near_b - far_b, 0.0)
    g_nx, g_ny = _width_adjoints(nx, ny, g_a, g_b)
    g_nx = g_nx + g_tlo * lo_nx + g_thi * hi_nx
    g_ny = g_ny + g_tlo * lo_ny + g_thi * hi_ny

    partials = (g_sd, g_far, g_nx, g_ny, g_r, g_tp, g_lp, g_tn)
    out = jnp.zeros_like(raw)
    for partial_, tangent in zip(partials, tangents[:8], strict=True):
        if not _is_zero(tangent):
            out = out + partial_ * tangent
    return jnp.clip(raw, 0.0, 1.0), out


_capsule.defjvp(_capsule_jvp, symbolic_zeros=True)


def _sliver_partials(lo, hi, t0, t1, t2) -> tuple[Array, Array, Array, Array, Array]:
    """The partials of ``sliver_integral(lo, hi, t0, t1, t2)`` in each argument."""
    # the parabola between the clipped ends A, B
    a, b = jnp.clip(lo, t1, t2), jnp.clip(hi, t1, t2)
    p_a, p_b = -0.5 * (a - t0) ** 2, 0.5 * (b - t0) ** 2
    p_lo = jnp.where((lo > t1) & (lo < t2), p_a, 0.0)
    p_hi = jnp.where((hi > t1) & (hi < t2), p_b, 0.0)
    p_1 = jnp.where(lo <= t1, p_a, 0.0) + jnp.where(hi <= t1, p_b, 0.0)
    p_2 = jnp.where(lo >= t2, p_a, 0.0) + jnp.where(hi >= t2, p_b, 0.0)
    p_0 = -(p_a + p_b)

    # each tangent piece is c u m: c = tk - t0, u = e2 - e1, m = (e1 + e2 - tk - t0) / 2
    def piece(e1, e2, tk):
        c, u = tk - t0, e2 - e1
        m = 0.5 * (e1 + e2) - 0.5 * (tk + t0)
        return c * (0.5 * u - m), c * (0.5 * u + m), u * m - 0.5 * c * u, -u * m - 0.5 * c * u

    left_1, left_2, left_k, left_0 = piece(jnp.minimum(lo, t1), jnp.minimum(hi, t1), t1)
    p_lo = p_lo + jnp.where(lo < t1, left_1, 0.0)
    p_hi = p_hi + jnp.where(hi < t1, left_2, 0.0)
    p_1 = p_1 + left_k + jnp.where(lo < t1, 0.0, left_1) + jnp.where(hi < t1, 0.0, left_2)
    right_1, right_2, right_k, right_0 = piece(jnp.maximum(lo, t2), jnp.maximum(hi, t2), t2)
    p_lo = p_lo + jnp.where(lo > t2, right_1, 0.0)
    p_hi = p_hi + jnp.where(hi > t2, right_2, 0.0)
    p_2 = p_2 + right_k + jnp.where(lo > t2, 0.0, right_1) + jnp.where(hi > t2, 0.0, right_2)
    return p_lo, p_hi, p_0 + left_0 + right_0, p_1, p_2


def _width_adjoints(nx: Array, ny: Array, g_a: Array, g_b: Array) -> tuple[Array, Array]:
    """Partials in ``nx``, ``ny`` from those in ``a = max(|nx|, |ny|)``, ``b = min(...)``."""
    ax, ay = jnp.abs(nx), jnp.abs(ny)
    x_is_a = ax >= ay
    g_a = jnp.where(jnp.maximum(ax, ay) > _MIN_WIDTH, g_a, 0.0)
    g_b = jnp.where(jnp.minimum(ax, ay) > _MIN_WIDTH, g_b, 0.0)
    g_x = jnp.where(x_is_a, g_a, g_b) * jnp.sign(nx)
    g_y = jnp.where(x_is_a, g_b, g_a) * jnp.sign(ny)
    return g_x, g_y
