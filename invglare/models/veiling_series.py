"""Fourier series of radially symmetric ghosts: coefficients, aggregation, evaluation.

The building blocks of Lee's *Parametric Veiling-Glare Rendering* (sec. 4-7),
written as pure `jax.numpy` functions (the model is
:class:`invglare.models.veiling.VeilingGlare`).

**Series.** A screen of ``ny x nx`` pixels is covered by one period of a 2-D
Fourier series whose period ``lam`` is twice the larger screen dimension (sec. 4.1),
so the periodic copies of anything inside the screen stay outside it. With
``w = 2 pi / lam``, ``c_n(x) = cos(n w x)`` and ``s_n(x) = sin(n w x)``, the image is
(eq. 18-19, 26)::

    F(x, y) = sum_{n, m = 0..N} A_nm c_n(x) c_m(y) + B_nm c_n(x) s_m(y)
                              + C_nm s_n(x) c_m(y) + D_nm s_n(x) s_m(y).

Index ``n`` goes with x and ``m`` with y throughout, and arrays of coefficients are
indexed ``[n, m]``.

**One ghost.** A ghost centred at the origin with a radially symmetric profile is
even in x and in y, so only its cosine-cosine coefficients survive (eq. 9, with
the integral over one period)::

    a_nm = kappa_nm / lam^2 * Fhat(nu_nm),     nu_nm = sqrt(n^2 + m^2) / lam,

where ``Fhat`` is the profile's 2-D Fourier transform (its Hankel transform) and
``kappa`` is 1, 2 or 4 (eq. 11-13). :func:`radial_spectrum` gives ``Fhat`` for the
profiles of :data:`PROFILES`, all with a peak ``intensity`` and a support
``radius``:

- ``"disk"``: the uniform disk (the boxcar of sec. 5.1), in closed form:
  ``I pi R^2 jinc(2 pi nu R)`` with ``jinc(x) = 2 J1(x) / x``;
- ``"hat"``: the autocorrelation of a disk of radius ``R / 2`` scaled to peak ``I``,
  a cone-like profile that is the 2-D counterpart of the triangle wave suggested in
  sec. 7.6 (a triangle is the self-convolution of a boxcar), also in closed form:
  ``I (pi R^2 / 4) jinc^2(pi nu R)``;
- ``"cosine"``: the raised cosine ``I (1 + cos(pi r / R)) / 2``, which has no closed
  form; its Hankel transform is integrated by a fixed Gauss–Legendre rule after an
  integration by parts that turns it into a superposition of disks (the boxcar
  superposition the paper's sec. 5.1 alludes to), so that only ``jinc`` is needed:
  ``Fhat(nu) = I R^2 int_0^1 (pi/2) sin(pi u) pi u^2 jinc(2 pi nu R u) du``.

Every profile can be given *smooth edges* by a Gaussian blur of standard deviation
``softness`` (a factor ``exp(-2 pi^2 softness^2 nu^2)``), which keeps the closed
forms closed and removes most of the ringing at its source.

**Translation and aggregation.** Moving a ghost to ``(x_k, y_k)`` turns its
coefficients into the four families of eq. 20-23 (the angle-difference identities
of eq. 16-17). Summing them over all ghosts (:func:`aggregate_coefficients`) gives
one set ``A, B, C, D`` whatever the number of ghosts, so the per-pixel cost is
``O(N)`` and independent of it; the ghost work is ``O(K N^2)``.

**Separable evaluation** (sec. 4.4, eq. 27-28): with the basis matrices
``Cx[i, n] = c_n(x_i)`` etc., the image is two matrix products,
``(Cy A^T + Sy B^T) Cx^T + (Cy C^T + Sy D^T) Sx^T``, first along ``m`` then along ``n``.

**Weights.** Per-harmonic weights multiply the basis (they are separable, so they
cost nothing per pixel): the sigma factors of :func:`sigma_factors` (sec. 4.5-4.6) and
the pixel-averaging factor ``sinc(n w p / 2)`` that turns point samples into the
mean over each pixel of pitch ``p``.
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from invglare._core.checks import as_float, choose
from invglare.errors import ConfigError
from invglare.optics.bessel import jinc

__all__ = [
    "PROFILES",
    "WINDOWS",
    "SeriesCoefficients",
    "aggregate_coefficients",
    "basis_matrices",
    "boxcar_coefficients",
    "evaluate_direct",
    "evaluate_separable",
    "ghost_coefficients",
    "kappa",
    "pixel_average_factors",
    "profile_area",
    "profile_values",
    "radial_spectrum",
    "sigma_factors",
    "translate_coefficients",
]

#: Radial ghost profiles with their spectrum (see the module docstring).
PROFILES = ("disk", "hat", "cosine")
#: De-ringing windows: Lanczos sigma factors (sec. 4.5) or Fejér (Cesàro) weights.
WINDOWS = ("lanczos", "fejer")

# Area under each profile of unit peak and unit radius: Fhat(0) / (I R^2).
_UNIT_AREA = {
    "disk": math.pi,
    "hat": math.pi / 4.0,
    "cosine": math.pi * (0.5 - 2.0 / math.pi**2),
}



def _check_harmonics(n_harmonics) -> int:
    if isinstance(n_harmonics, bool) or not isinstance(n_harmonics, int | np.integer):
        raise ConfigError(f"n_harmonics must be an integer >= 1, got {n_harmonics!r}")
    if n_harmonics < 1:
        raise ConfigError(f"n_harmonics must be an integer >= 1, got {n_harmonics}")
    return int(n_harmonics)


# ------------------------------------------------------------------------------ profiles


def profile_area(profile: str) -> float:
    """Integral of a profile of unit peak and unit radius (multiply by ``I R^2``).

    **Example:**

    ```python
    profile_area("disk")   # pi
    ```
    """
    choose("profile", profile, PROFILES)
    return _UNIT_AREA[profile]


def profile_values(
    profile: str,
    r: Float[ArrayLike, "*shape"],
    radius: Float[ArrayLike, "*shape"],
    intensity: Float[ArrayLike, "*shape"] = 1.0,
) -> Float[Array, "*shape"]:
    """The (unblurred) profile at distance `r` from the ghost's centre.

    Meant for references and tests (hard edges are not differentiable in `radius`).

    **Example:**

    ```python
    profile_values("hat", 0.0, 1.0)   # 1.0, the peak
    ```
    """
    choose("profile", profile, PROFILES)
    u = jnp.abs(as_float(r)) / as_float(radius)
    inside = u < 1.0
    uc = jnp.clip(u, 0.0, 1.0)
    if profile == "disk":
        shape = jnp.ones_like(uc)
    elif profile == "hat":
        shape = (2.0 / math.pi) * (jnp.arccos(uc) - uc * jnp.sqrt(1.0 - uc * uc))
    else:
        shape = 0.5 * (1.0 + jnp.cos(math.pi * uc))
    return jnp.where(inside, shape, 0.0) * as_float(intensity)


# Where the "cosine" quadrature's spectrum is tapered off, in units of the node count.
_TAPER_START, _TAPER_END = 2.5, 2.8


@functools.cache
def _gauss_legendre(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Nodes and weights on [0, 1]."""
    x, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * (x + 1.0), 0.5 * w


def radial_spectrum(
    profile: str,
    nu: Float[ArrayLike, "*shape"],
    radius: Float[ArrayLike, "*shape"],
    intensity: Float[ArrayLike, "*shape"] = 1.0,
    softness: Float[ArrayLike, "*shape"] = 0.0,
    quadrature_nodes: int = 48,
) -> Float[Array, "*shape"]:
    """2-D Fourier transform ``Fhat(nu)`` of a centred ghost, at radial frequency `nu`.

    **Arguments:**

    - `profile`: one of :data:`PROFILES`.
    - `nu`: radial spatial frequency (cycles per unit of length; the model uses deg).
    - `radius`: support radius ``R`` (same length unit).
    - `intensity`: peak value ``I`` of the unblurred profile.
    - `softness`: standard deviation of the Gaussian edge blur (length unit; 0: none).
    - `quadrature_nodes`: Gauss–Legendre nodes ``Q`` for ``"cosine"`` (static). The
      rule is exact to ~1e-9 of the peak while ``2 pi nu R < 2.9 Q``; the spectrum is
      tapered to zero between ``2.5 Q`` and ``2.8 Q``, where it is already below ~1e-6
      of its peak (for ``Q = 48``), rather than letting the rule's error through.

    All array arguments broadcast. Units: ``intensity x length^2``.

    **Example:**

    ```python
    radial_spectrum("disk", 0.0, 2.0, 1.0)   # 4 pi: the disk's area
    ```
    """
    choose("profile", profile, PROFILES)
    nu, radius = as_float(nu), as_float(radius)
    intensity, softness = as_float(intensity), as_float(softness)
    if profile == "disk":
        shape = math.pi * radius**2 * jinc(2.0 * math.pi * nu * radius)
    elif profile == "hat":
        shape = 0.25 * math.pi * radius**2 * jinc(math.pi * nu * radius) ** 2
    else:
        u, w = _gauss_legendre(int(quadrature_nodes))
        u = jnp.asarray(u, dtype=nu.dtype)
        # -g'(u) = (pi / 2) sin(pi u): the weight of the disk of radius u R.
        weight = jnp.asarray(w, dtype=nu.dtype) * (0.5 * math.pi) * jnp.sin(math.pi * u)
        x = 2.0 * math.pi * nu * radius
        shape = radius**2 * jnp.sum(weight * math.pi * u**2 * jinc(x[..., None] * u), axis=-1)
        # The rule is exact to ~1e-9 up to x ~ 2.9 Q and then fails; the true spectrum
        # there is below ~1e-6 of the peak, so it is tapered to zero over [2.5, 2.8] Q
        # (smoothly, so that gradients in R and nu stay continuous).
        x0, x1 = _TAPER_START * quadrature_nodes, _TAPER_END * quadrature_nodes
        t = jnp.clip((x - x0) / (x1 - x0), 0.0, 1.0)
        shape = shape * (0.5 + 0.5 * jnp.cos(math.pi * t))
    blur = jnp.exp(-2.0 * math.pi**2 * (softness * nu) ** 2)
    return intensity * shape * blur


# ------------------------------------------------------------------------------ coefficients


class SeriesCoefficients(eqx.Module):
    """The four coefficient families of eq. 18-19, each indexed ``[n, m]`` (n: x, m: y).

    ``A``: ``c_n(x) c_m(y)``, ``B``: ``c_n(x) s_m(y)``, ``C``: ``s_n(x) c_m(y)``,
    ``D``: ``s_n(x) s_m(y)``. Leading batch axes (one set per ghost) are allowed.
    """

    A: Float[Array, "*batch N1 M1"]
    B: Float[Array, "*batch N1 M1"]
    C: Float[Array, "*batch N1 M1"]
    D: Float[Array, "*batch N1 M1"]

    def __add__(self, other: SeriesCoefficients) -> SeriesCoefficients:
        return jax.tree_util.tree_map(jnp.add, self, other)

    def sum(self, axis: int = 0) -> SeriesCoefficients:
        """Sum over a batch axis (aggregation of several ghosts)."""
        return jax.tree_util.tree_map(lambda a: jnp.sum(a, axis=axis), self)


# Arguments fixed at trace time for the coefficient functions (jitted so that eager
# callers compile one program per configuration).
_COEFF_STATIC = ("profile", "n_harmonics", "period", "quadrature_nodes")


def kappa(n_harmonics: int) -> np.ndarray:
    """Normalisation ``kappa_nm`` of eq. 11-13: 1 at (0, 0), 2 on the axes, 4 elsewhere."""
    n = _check_harmonics(n_harmonics)
    k1 = np.where(np.arange(n + 1) == 0, 1.0, 2.0)
    return k1[:, None] * k1[None, :]


def boxcar_coefficients(
    intensity: Float[ArrayLike, ""],
    half_width: Float[ArrayLike, ""],
    n_harmonics: int,
    period: float,
) -> Float[Array, " N1"]:
    """Cosine-series coefficients of the 1-D boxcar ``I`` on ``[-r, r]`` (eq. 38-40).

    ``a_0 = 2 I r / lam`` and ``a_n = 4 I s_n(r) / (n w lam)``, for ``n = 1..N``.

    **Arguments:**

    - `intensity`: the boxcar's height ``I``.
    - `half_width`: ``r`` (same unit as `period`).
    - `n_harmonics`: ``N``.
    - `period`: ``lam``.

    **Example:**

    ```python
    a = boxcar_coefficients(1.0, 10.0, 64, 100.0)   # a[0] = 0.2
    ```
    """
    n = jnp.arange(_check_harmonics(n_harmonics) + 1)
    intensity, r = as_float(intensity), as_float(half_width)
    w = 2.0 * math.pi / period
    safe_n = jnp.where(n == 0, 1, n)
    a = 4.0 * intensity * jnp.sin(safe_n * w * r) / (safe_n * w * period)
    return jnp.where(n == 0, 2.0 * intensity * r / period, a)


@functools.partial(jax.jit, static_argnames=_COEFF_STATIC)
def ghost_coefficients(
    profile: str,
    intensity: Float[ArrayLike, " K"],
    radius: Float[ArrayLike, " K"],
    softness: Float[ArrayLike, " K"],
    n_harmonics: int,
    period: float,
    quadrature_nodes: int = 48,
) -> Float[Array, "K N1 N1"]:
    """Cosine-cosine coefficients ``a_knm`` of centred ghosts (eq. 24).

    **Arguments:**

    - `profile`: one of :data:`PROFILES` (shared by all ghosts).
    - `intensity`, `radius`, `softness`: per ghost, as for :func:`radial_spectrum`.
    - `n_harmonics`: ``N`` (the series runs over ``n, m = 0..N``).
    - `period`: ``lam`` (same length unit as `radius`).
    - `quadrature_nodes`: for ``"cosine"``.

    **Example:**

    ```python
    a = ghost_coefficients("disk", jnp.ones(3), jnp.array([5.0, 8, 12]), jnp.zeros(3), 32, 200.0)
    ```
    """
    n = _check_harmonics(n_harmonics)
    intensity, radius, softness = as_float(intensity), as_float(radius), as_float(softness)
    wx, wy = _separable_weights(intensity, softness, n, period)
    spectrum = _unit_spectrum(profile, radius, n, period, quadrature_nodes)
    return spectrum * wx[:, :, None] * wy[:, None, :]


def _unit_spectrum(
    profile: str, radius: Array, n_harmonics: int, period: float, quadrature_nodes: int
) -> Array:
    """``Fhat(nu_nm)`` of unit-intensity, hard-edged ghosts: (K, N+1, N+1)."""
    k = np.arange(n_harmonics + 1)
    nu = jnp.asarray(np.sqrt(k[:, None] ** 2 + k[None, :] ** 2) / period, dtype=radius.dtype)
    return radial_spectrum(profile, nu, radius[:, None, None], 1.0, 0.0, quadrature_nodes)


def _separable_weights(
    intensity: Array, softness: Array, n_harmonics: int, period: float
) -> tuple[Array, Array]:
    """The factors of ``a_knm`` that are products of a function of n and one of m.

    The edge blur ``exp(-2 pi^2 s^2 nu^2)``, ``kappa`` and ``I / lam^2`` split into
    ``wx[k, n] wy[k, m]``, so they cost O(N) per ghost instead of O(N^2).
    """
    k = jnp.arange(n_harmonics + 1, dtype=softness.dtype)
    k1 = jnp.where(k == 0, 1.0, 2.0)
    wy = k1 * jnp.exp(-2.0 * (math.pi / period) ** 2 * softness[:, None] ** 2 * k**2)
    return wy * (intensity / period**2)[:, None], wy


def _phases(position: Float[Array, "K 2"], n_harmonics: int, period: float):
    k = jnp.arange(n_harmonics + 1, dtype=position.dtype)
    w = 2.0 * math.pi / period
    px = w * position[:, 0, None] * k  # (K, N+1)
    py = w * position[:, 1, None] * k
    return jnp.cos(px), jnp.sin(px), jnp.cos(py), jnp.sin(py)


@functools.partial(jax.jit, static_argnames=("period",))
def translate_coefficients(
    a: Float[Array, "K N1 M1"],
    b: Float[Array, "K N1 M1"] | None,
    position: Float[ArrayLike, "K 2"],
    period: float,
) -> SeriesCoefficients:
    """Coefficients of ghosts moved to `position` (eq. 20-23, one set per ghost).

    **Arguments:**

    - `a`, `b`: the centred ghosts' cosine-cosine and sine-sine coefficients; `b`
      may be ``None`` for even profiles (every radially symmetric one), where it is 0.
    - `position`: ``(x_k, y_k)`` per ghost (same unit as `period`).
    - `period`: ``lam``.

    **Example:**

    ```python
    moved = translate_coefficients(a, None, jnp.array([[3.0, -1.0]]), 200.0)
    ```
    """
    position = as_float(position)
    n = a.shape[-2] - 1
    if a.shape[-1] != a.shape[-2]:
        raise ConfigError(f"coefficients must be square (N+1, N+1), got shape {a.shape}")
    cx, sx, cy, sy = _phases(position, n, period)
    cc = cx[:, :, None] * cy[:, None, :]
    cs = cx[:, :, None] * sy[:, None, :]
    sc = sx[:, :, None] * cy[:, None, :]
    ss = sx[:, :, None] * sy[:, None, :]
    if b is None:
        return SeriesCoefficients(A=a * cc, B=a * cs, C=a * sc, D=a * ss)
    return SeriesCoefficients(
        A=a * cc + b * ss, B=a * cs - b * sc, C=a * sc - b * cs, D=a * ss + b * cc
    )


def default_chunk(
    n_harmonics: int, profile: str, quadrature_nodes: int = 48, n_ghosts: int | None = None
) -> int:
    """Ghosts per aggregation step: 16 (fewer past ~4M evaluations), or 1 below 16 ghosts.

    Measured on 2 CPU cores (float32), one aggregation: 16 ghosts a step against 1 was
    2x faster for 100 and 1000 ghosts at N = 64 and 256, and 32 no better; but a step
    of 2 to 15 ghosts runs slowly on XLA's CPU code (10 ghosts at N = 256: 16 ms in
    one step, 4.9 ms in steps of 1), so fewer than 16 ghosts go one at a time.
    """
    if n_ghosts is not None and n_ghosts < 16:
        return 1
    per_ghost = (n_harmonics + 1) ** 2 * (quadrature_nodes if profile == "cosine" else 1)
    return max(1, min(16, 4_000_000 // per_ghost))


@functools.partial(jax.jit, static_argnames=(*_COEFF_STATIC, "chunk"))
def aggregate_coefficients(
    profile: str,
    intensity: Float[ArrayLike, " K"],
    radius: Float[ArrayLike, " K"],
    softness: Float[ArrayLike, " K"],
    position: Float[ArrayLike, "K 2"],
    n_harmonics: int,
    period: float,
    quadrature_nodes: int = 48,
    chunk: int | None = None,
) -> SeriesCoefficients:
    """One set of coefficients ``A, B, C, D`` for all ghosts together (eq. 20-25).

    Ghosts are processed `chunk` at a time (`lax.scan`), and each ghost's
    coefficients are added into the four sums as soon as they are made, so the
    work per ghost stays in cache and memory stays at ``chunk x (N+1)^2`` however
    many ghosts there are; ghosts of zero intensity pad the last chunk and add nothing.

    **Arguments:** as for :func:`ghost_coefficients`, plus the ghosts' `position`
    ``(K, 2)`` and `chunk` (default: :func:`default_chunk`).

    **Example:**

    ```python
    coeffs = aggregate_coefficients("disk", i, r, s, p, 64, 2 * 512 * 0.01)
    ```
    """
    n = _check_harmonics(n_harmonics)
    intensity, radius = as_float(intensity), as_float(radius)
    softness, position = as_float(softness), as_float(position)
    dtype = jnp.result_type(intensity, radius, softness, position)
    k = intensity.shape[0]
    if not (radius.shape == softness.shape == (k,) and position.shape == (k, 2)):
        raise ConfigError(
            "ghost arrays must be intensity (K,), radius (K,), softness (K,), position (K, 2); "
            f"got {intensity.shape}, {radius.shape}, {softness.shape}, {position.shape}"
        )
    if chunk is None:
        chunk = default_chunk(n, profile, quadrature_nodes, k)
    chunk = max(1, min(chunk, k)) if k else 1
    n_chunks = max(1, -(-k // chunk))
    pad = n_chunks * chunk - k

    def padded(x, fill):
        x = jnp.asarray(x, dtype=dtype)
        widths = [(0, pad)] + [(0, 0)] * (x.ndim - 1)
        return jnp.pad(x, widths, constant_values=fill).reshape(n_chunks, chunk, *x.shape[1:])

    # Everything but the radial spectrum is separable and made before the scan:
    # inside it, XLA would fuse each cos/sin/exp into the (N+1)^2 products below and
    # evaluate it (N+1) times over.
    wx, wy = _separable_weights(intensity, softness, n, period)
    cx, sx, cy, sy = _phases(position, n, period)
    xs = (
        padded(radius, 1.0),  # padding ghosts: unit radius, zero weight
        padded(cx * wx, 0.0),
        padded(sx * wx, 0.0),
        padded(cy * wy, 0.0),
        padded(sy * wy, 0.0),
    )

    def one_chunk(total: SeriesCoefficients, ghosts):
        r, cx, sx, cy, sy = ghosts
        a = _unit_spectrum(profile, r, n, period, quadrature_nodes)
        # sum_k a_knm x_kn y_km is not a matrix product; written as an einsum or a
        # reduction over k, XLA's CPU code is ~40x slower than these per-ghost
        # multiply-adds (measured at K = 1000, N = 256).
        big_a, big_b, big_c, big_d = total.A, total.B, total.C, total.D
        for g in range(chunk):
            along_cy, along_sy = a[g] * cy[g][None, :], a[g] * sy[g][None, :]
            big_a = big_a + along_cy * cx[g][:, None]
            big_b = big_b + along_sy * cx[g][:, None]
            big_c = big_c + along_cy * sx[g][:, None]
            big_d = big_d + along_sy * sx[g][:, None]
        return SeriesCoefficients(A=big_a, B=big_b, C=big_c, D=big_d), None

    zero = jnp.zeros((n + 1, n + 1), dtype=dtype)
    init = SeriesCoefficients(A=zero, B=zero, C=zero, D=zero)
    total, _ = jax.lax.scan(one_chunk, init, xs)
    return total


# ------------------------------------------------------------------------------ weights


def sigma_factors(
    n_harmonics: int, strength: Float[ArrayLike, ""] = 1.0, window: str = "lanczos"
) -> Float[Array, " N1"]:
    """Per-harmonic de-ringing weights ``sigma_n`` for ``n = 0..N`` (sec. 4.5-4.6).

    - ``"lanczos"``: ``sinc(n / (N + 1)) ** strength`` (normalised sinc). Strength 1
      is Lanczos' sigma-approximation (eq. 29); 0 is the plain truncated series;
      larger values smooth more. The paper's ``sinc(n / N)`` would zero the last
      harmonic outright; dividing by ``N + 1`` keeps every computed term.
    - ``"fejer"``: ``(1 - n / (N + 1)) ** strength``, the Cesàro mean. Its kernel is
      non-negative for integer strengths >= 1, so a non-negative image stays
      non-negative (at the price of more blur than Lanczos).

    Applied to both axes, ``sigma_n sigma_m`` weights every term (eq. 34); the DC term
    keeps weight 1 (the paper's sums from 1 would drop the mean).

    **Example:**

    ```python
    sigma_factors(4)   # [1, 0.935, 0.757, 0.505, 0.234]
    ```
    """
    n = _check_harmonics(n_harmonics)
    choose("window", window, WINDOWS)
    strength = as_float(strength)
    t = jnp.arange(n + 1, dtype=strength.dtype) / (n + 1)
    base = jnp.sinc(t) if window == "lanczos" else 1.0 - t
    # base > 0 for t < 1; the power keeps strength differentiable.
    return jnp.exp(strength * jnp.log(base))


def pixel_average_factors(
    n_harmonics: int, pitch: Float[ArrayLike, ""], period: float
) -> Float[Array, " N1"]:
    """``sinc(n w p / 2)``: the mean of ``c_n`` or ``s_n`` over a pixel of pitch `p`, per unit.

    **Example:**

    ```python
    pixel_average_factors(64, 0.01, 10.24)
    ```
    """
    n = _check_harmonics(n_harmonics)
    pitch = as_float(pitch)
    # jnp.sinc is sin(pi t) / (pi t): with t = n p / lam this is sin(n w p / 2) / (n w p / 2).
    return jnp.sinc(jnp.arange(n + 1, dtype=pitch.dtype) * pitch / period)


# ------------------------------------------------------------------------------ evaluation


def basis_matrices(
    coords: Float[ArrayLike, " P"],
    n_harmonics: int,
    period: float,
    weights: Float[ArrayLike, " N1"] | None = None,
) -> tuple[Float[Array, "P N1"], Float[Array, "P N1"]]:
    """``C[i, n] = weight_n c_n(x_i)`` and ``S[i, n] = weight_n s_n(x_i)``.

    **Example:**

    ```python
    cx, sx = basis_matrices(jnp.linspace(-1, 1, 5), 8, 4.0)
    ```
    """
    n = _check_harmonics(n_harmonics)
    coords = as_float(coords)
    phase = (2.0 * math.pi / period) * coords[:, None] * jnp.arange(n + 1, dtype=coords.dtype)
    c, s = jnp.cos(phase), jnp.sin(phase)
    if weights is not None:
        weights = jnp.asarray(weights, dtype=coords.dtype)
        c, s = c * weights, s * weights
    return c, s


@functools.partial(jax.jit, static_argnames=("period",))
def evaluate_separable(
    coeffs: SeriesCoefficients,
    x: Float[ArrayLike, " nx"],
    y: Float[ArrayLike, " ny"],
    period: float,
    weights_x: Float[ArrayLike, " N1"] | None = None,
    weights_y: Float[ArrayLike, " N1"] | None = None,
) -> Float[Array, "ny nx"]:
    """The series on the grid ``y x x`` by two matrix products (sec. 4.4, eq. 27-28).

    Cost ``O(ny N^2 + ny nx N)``: first each row's sums over ``m``, then over ``n``.

    **Arguments:**

    - `coeffs`: aggregated coefficients (no batch axis).
    - `x`, `y`: pixel-centre coordinates of the columns and rows.
    - `period`: ``lam``.
    - `weights_x`, `weights_y`: per-harmonic weights (sigma factors, pixel averaging).

    **Returns:** ``(ny, nx)``, row ``j`` at ``y[j]``, column ``i`` at ``x[i]``.

    **Example:**

    ```python
    image = evaluate_separable(coeffs, xs, ys, period)
    ```
    """
    n = coeffs.A.shape[0] - 1
    cx, sx = basis_matrices(x, n, period, weights_x)
    cy, sy = basis_matrices(y, n, period, weights_y)
    # Stage 1 (along m): rows (ny, N+1) multiplying c_n(x) and s_n(x).
    along_c = cy @ coeffs.A.T + sy @ coeffs.B.T
    along_s = cy @ coeffs.C.T + sy @ coeffs.D.T
    # Stage 2 (along n).
    return along_c @ cx.T + along_s @ sx.T


@functools.partial(jax.jit, static_argnames=("period",))
def evaluate_direct(
    coeffs: SeriesCoefficients,
    x: Float[ArrayLike, " nx"],
    y: Float[ArrayLike, " ny"],
    period: float,
    weights_x: Float[ArrayLike, " N1"] | None = None,
    weights_y: Float[ArrayLike, " N1"] | None = None,
) -> Float[Array, "ny nx"]:
    """The same image by the plain double sum at every pixel (eq. 26): a slow reference.

    Cost ``O(ny nx N^2)``; pixels are processed one row at a time.

    **Example:**

    ```python
    reference = evaluate_direct(coeffs, xs, ys, period)
    ```
    """
    n = coeffs.A.shape[0] - 1
    x, y = as_float(x), as_float(y)
    k = jnp.arange(n + 1, dtype=x.dtype)
    w = 2.0 * math.pi / period
    wx = jnp.ones(n + 1, x.dtype) if weights_x is None else jnp.asarray(weights_x, x.dtype)
    wy = jnp.ones(n + 1, x.dtype) if weights_y is None else jnp.asarray(weights_y, x.dtype)
    g = jnp.stack([coeffs.A, coeffs.B, coeffs.C, coeffs.D]) * (wx[:, None] * wy[None, :])

    def pixel(xi, yj):
        cn, sn = jnp.cos(k * w * xi), jnp.sin(k * w * xi)
        cm, sm = jnp.cos(k * w * yj), jnp.sin(k * w * yj)
        terms = (
            g[0] * cn[:, None] * cm[None, :]
            + g[1] * cn[:, None] * sm[None, :]
            + g[2] * sn[:, None] * cm[None, :]
            + g[3] * sn[:, None] * sm[None, :]
        )
        return jnp.sum(terms)

    row = jax.vmap(pixel, in_axes=(0, None))
    return jax.lax.map(lambda yj: row(x, yj), y)
