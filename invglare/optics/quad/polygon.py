"""Exact Fourier transforms of polygons, disks and ellipses, differentiable in their geometry.

**Polygons** (Lee & Mittra 1983). For a simple polygon with counter-clockwise vertices, the
divergence theorem turns the area integral of ``exp(-2 pi i f.r)`` into a sum over edges
``e = b - a`` with midpoints ``m``:

    F(f) = i / (2 pi |f|^2)  sum_edges (f_x e_y - f_y e_x) exp(-2 pi i f.m) sinc(f.e),

``sinc(u) = sin(pi u) / (pi u)``. The classical singular directions ``f`` perpendicular to
an edge (``f.e = 0``) are regular in this form; the sinc is the one of
:func:`invglare.optics.quad.transform.sinc`, exact in value and derivative there. Away from
them it is evaluated as ``(exp(-2 pi i f.a) - exp(-2 pi i f.b)) / (2 pi i f.e)``, with the
vertices' plane waves separable on an output grid.

Only ``f -> 0`` is singular: the edge terms, each of order ``L / |f|``, cancel to the area,
losing digits as ``eps / (|f| R)``. There (``2 pi |f| R < 1``, ``R`` the largest distance of
a vertex from the vertex centroid ``c``) the polygon is the fan of triangles ``(c, a, b)``
and each is expanded in a power series (Wuttke 2021, J. Appl. Cryst. 54, "Numerically
stable form factor of any polygon and polyhedron"):

    int_T exp(l(r)) dA = (a - c) x (b - c) sum_n h_n(l_a, l_b) / (n + 2)!,

``l_v = -2 pi i f.(v - c)``, ``h_n`` the complete homogeneous polynomial of degree ``n``
(recurrence ``h_n = l_a h_{n-1} + l_b^n``), 16 orders (truncation below 1e-16 there). It is
evaluated only at the few output frequencies that need it (a static index set).

**Disks and ellipses** have their exact transforms, ``pi a b jinc(2 pi |A^T f|)``.

Every transform here is a pure function of the vertices (or centre, axes, rotation): a
fitted blade rotation or a lash angle has an exact gradient with no raster.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Complex, Float, Int

from invglare.optics.bessel import jinc
from invglare.optics.quad.transform import sinc

#: Orders of the small-frequency series (its terms fall as 1 / (n + 2)! below 2 pi |f| R = 1).
SERIES_ORDER = 16
#: The series is used where ``2 pi |f| R`` is below this.
SERIES_BELOW = 1.0


def _plane_wave(coord: Float[Array, " m"], pos: Float[Array, ""]) -> Complex[Array, " m"]:
    angle = (-2.0 * math.pi) * (coord * pos)
    return jax.lax.complex(jnp.cos(angle), jnp.sin(angle))


def _edge_sum(
    vertices: Float[Array, "v 2"], fy: Float[Array, " ny"], fx: Float[Array, " nx"]
) -> Complex[Array, "ny nx"]:
    """``sum_edges (f x e) exp(-2 pi i f.m) sinc(f.e)`` on the grid ``fy x fx``."""
    a = vertices
    b = jnp.roll(vertices, -1, axis=0)
    fxg, fyg = fx[None, :], fy[:, None]

    @jax.checkpoint
    def edge(acc, ab):
        (ax, ay), (bx, by) = ab
        ex, ey = bx - ax, by - ay
        u = fxg * ex + fyg * ey
        cross = fxg * ey - fyg * ex
        wave_a = _plane_wave(fy, ay)[:, None] * _plane_wave(fx, ax)[None, :]
        wave_b = _plane_wave(fy, by)[:, None] * _plane_wave(fx, bx)[None, :]
        small = jnp.abs(math.pi * u) < 1.0
        u_safe = jnp.where(small, 1.0, u)
        # sin(pi u) exp(-2 pi i f.m) = (wave_a - wave_b) / (2 i): no sine per pixel.
        far = (wave_a - wave_b) / (2j * math.pi * u_safe)
        wave_m = (
            _plane_wave(fy, 0.5 * (ay + by))[:, None] * _plane_wave(fx, 0.5 * (ax + bx))[None, :]
        )
        near = wave_m * sinc(jnp.where(small, u, 0.0))
        return acc + cross * jnp.where(small, near, far), None

    zero = jnp.zeros((fy.shape[0], fx.shape[0]), jnp.result_type(fy, 1j))
    total, _ = jax.lax.scan(edge, zero, ((a[:, 0], a[:, 1]), (b[:, 0], b[:, 1])))
    return total


def _fan_series(
    vertices: Float[Array, "v 2"], fy: Float[Array, " k"], fx: Float[Array, " k"]
) -> Complex[Array, " k"]:
    """The transform at the points ``(fy[i], fx[i])`` by the triangle-fan power series."""
    centre = jnp.mean(vertices, axis=0)
    rel = vertices - centre
    a, b = rel, jnp.roll(rel, -1, axis=0)
    twice_area = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    k = (-2j * math.pi) * jnp.stack([fx, fy], axis=-1)  # (k, 2)
    la = k @ a.T.astype(k.dtype)  # (k, v)
    lb = k @ b.T.astype(k.dtype)
    h = jnp.ones_like(la)
    lb_pow = jnp.ones_like(lb)
    series = h / 2.0
    for n in range(1, SERIES_ORDER + 1):
        lb_pow = lb_pow * lb
        h = la * h + lb_pow
        series = series + h * (1.0 / math.factorial(n + 2))
    phase = jnp.exp((-2j * math.pi) * (fx * centre[0] + fy * centre[1]))
    return phase * jnp.sum(twice_area * series, axis=-1)


def series_points(
    fy: np.ndarray, fx: np.ndarray, radius_mm: float
) -> tuple[np.ndarray, np.ndarray]:
    """The grid points ``(row, col)`` of ``fy x fx`` with ``2 pi |f| radius < 1`` (numpy)."""
    r2 = fy[:, None] ** 2 + fx[None, :] ** 2
    rows, cols = np.nonzero(r2 < (SERIES_BELOW / (2.0 * math.pi * radius_mm)) ** 2)
    return rows, cols


def polygon_transform(
    vertices_mm: Float[Array, "v 2"],
    fy: Float[Array, " ny"],
    fx: Float[Array, " nx"],
    series_at: tuple[Int[np.ndarray, " k"], Int[np.ndarray, " k"]] | None = None,
) -> Complex[Array, "ny nx"]:
    """``int_P exp(-2 pi i f.r) dA`` (mm^2) of a polygon on the grid ``fy x fx`` (cycles/mm).

    **Arguments:**

    - `vertices_mm`: ``(v, 2)`` vertices ``(x, y)`` of a simple polygon, counter-clockwise
      for a positive area (clockwise gives the negative).
    - `fy`, `fx`: frequencies (cycles/mm) of the rows and columns.
    - `series_at`: the grid points ``(rows, cols)`` that may need the small-frequency series
      (numpy, static): those within ``1 / (2 pi R)`` of 0 for the largest `R` the vertices
      may reach from their centroid (:func:`series_points`). None: found from the
      frequencies and vertices, which must then be concrete.

    **Returns:** complex ``F`` (mm^2).
    """
    v = jnp.asarray(vertices_mm)
    dtype = jnp.result_type(v, fy, fx)
    v, fy, fx = v.astype(dtype), jnp.asarray(fy, dtype), jnp.asarray(fx, dtype)
    if series_at is None:
        if isinstance(v, jax.core.Tracer) or isinstance(fy, jax.core.Tracer):
            raise ValueError(
                "polygon_transform of traced vertices or frequencies needs series_at: the "
                "grid points near f = 0 (series_points with a bound on the polygon's radius)"
            )
        vv = np.asarray(v)
        radius = float(np.max(np.hypot(*(vv - vv.mean(axis=0)).T)))
        series_at = series_points(np.asarray(fy), np.asarray(fx), radius)
    rows, cols = series_at
    r2 = fy[:, None] ** 2 + fx[None, :] ** 2
    # Away from the series points the division by |f|^2 is safe; at them it is replaced.
    at_zero = r2 == 0.0
    r2_safe = jnp.where(at_zero, 1.0, r2)
    out = (1j / (2.0 * math.pi)) * _edge_sum(v, fy, fx) / r2_safe
    if rows.size:
        centre = jnp.mean(v, axis=0)
        radius = jnp.sqrt(jnp.max(jnp.sum((v - centre) ** 2, axis=-1)))
        fy_k, fx_k = fy[rows], fx[cols]
        series = _fan_series(v, fy_k, fx_k)
        use = (2.0 * math.pi) ** 2 * (fy_k**2 + fx_k**2) * radius**2 < SERIES_BELOW**2
        out = out.at[rows, cols].set(jnp.where(use, series, out[rows, cols]))
    return out


def ellipse_transform(
    centre_mm: Float[Array, " 2"],
    semi_axes_mm: Float[Array, " 2"],
    rotation_rad: Float[Array, ""],
    fy: Float[Array, " ny"],
    fx: Float[Array, " nx"],
) -> Complex[Array, "ny nx"]:
    """Exact transform of a uniform ellipse (a disk for equal semi-axes), mm^2.

    ``pi a b jinc(2 pi |(a f_u, b f_v)|) exp(-2 pi i f.c)`` with ``(f_u, f_v)`` the frequency
    in the ellipse's axes; ``jinc = 2 J1(x) / x`` (:func:`invglare.optics.bessel.jinc`).
    """
    a, b = semi_axes_mm[0], semi_axes_mm[1]
    c, s = jnp.cos(rotation_rad), jnp.sin(rotation_rad)
    fu = c * fx[None, :] + s * fy[:, None]
    fv = -s * fx[None, :] + c * fy[:, None]
    q2 = (a * fu) ** 2 + (b * fv) ** 2
    nonzero = q2 > 0.0
    q = jnp.where(nonzero, jnp.sqrt(jnp.where(nonzero, q2, 1.0)), 0.0)
    wave = _plane_wave(fy, centre_mm[1])[:, None] * _plane_wave(fx, centre_mm[0])[None, :]
    return (math.pi * a * b) * jinc(2.0 * math.pi * q) * wave
