"""The base layer: the field of all point sources at the first plane of the eye (sec. 2.3.2).

**Reference (eq. 2.2).** :func:`spherical_wave_sum` evaluates
``U(x) = sum_j a_j exp(i k r_j) / r_j``, ``r_j = |x - P_j|``, at every sample of the base
grid: ``N^2`` exponentials per source, the paper's bottleneck (about ``7e10`` per iteration
at 512 x 512). It is the reference for small sizes; run it in float64 (``k r`` is ``1e7``
rad at a metre, and float32 keeps no digit of its fraction).

**Fast path.** A source at ``(X, Y, z)`` seen from a window much smaller than ``z`` is, in
the Fresnel approximation, ``exp(i k z) exp(i pi |x - X|^2 / (lambda z)) / z``: a plane wave
of spatial frequency ``-X / (lambda z) = -tan(theta) / lambda`` times the curvature
``exp(i pi |x|^2 / (lambda z))`` (and a phase of its own, which the random phase absorbs).
On the holographic grid (:mod:`invglare.optics.holographic.sampling`) every output
pixel's direction *is* an FFT bin, so all sources at one depth give their plane waves in
one inverse FFT, and the depth enters as one curvature factor: the single-FFT Fresnel
transform from the source plane. With depth, the sources are grouped into layers of equal
vergence ``V = 1 / z`` (:func:`~invglare.optics.holographic.sources.layer_vergences`), one
inverse FFT and one curvature each (:func:`fresnel_base_field`); how many layers a depth
range needs is :func:`~invglare.optics.holographic.sampling.depth_layers_needed`.

**Why not the angular spectrum from each depth plane.** The band-limited angular
spectrum (Matsushima & Shimobaba 2009) carries a field between planes on one grid; it is
what the eye uses from layer to layer (mm apart). From a depth plane metres away it
fails twice: the sources lie far outside the window (a 40-degree frame at 2 m spans 1.5 m,
the window a few mm), and its band limit ``1 / (lambda sqrt((2 z / W)^2 + 1))`` keeps, for
``z = 2 m`` and ``W = 8 mm``, only directions within ``W / (2 z) = 0.1`` degree of the axis.
The Fresnel transform is exact (in the Fresnel approximation) for one constant depth.

**What the fast path approximates** (against eq. 2.2, per source at distance ``R`` and
direction cosine ``u``, over a window of half-width ``a``):

- direction: the plane wave has frequency ``tan(theta) / lambda``, not ``sin(theta) /
  lambda`` (perspective pixels): a phase error up to ``k a tan^3(theta) / 2`` at the edge;
- oblique curvature: a spherical wave met obliquely has curvature ``cos^2(theta) / R``
  along the tilt (astigmatism of the flat plane), here ``1 / z``: ``k a^2 u^2 / (2 R)``;
- higher orders: ``k a^4 / (8 R^3)`` and ``k a^3 u / (2 R^2)``.

For the paraxial fields the holographic grid can hold (``N dt`` of a few degrees) and
distances beyond a few hundred mm these are far below a radian; the tests check the fast
path against eq. 2.2 to 1e-4 where they are all below 1e-4 rad.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Complex, Float

from invglare._core.grids import ApertureGrid, nm_to_mm
from invglare.errors import ConfigError

__all__ = ["fresnel_base_field", "plane_wave_sum", "spherical_wave_sum"]


def spherical_wave_sum(
    amplitudes: Complex[ArrayLike, " s"],
    positions_mm: Float[ArrayLike, "s 3"],
    grid: ApertureGrid,
    wavelength_nm: ArrayLike,
    chunk: int = 256,
) -> Complex[Array, "n n"]:
    """Eq. 2.2 by brute force: ``sum_j a_j exp(i k r_j) / r_j`` on a centred grid at ``z = 0``.

    **Arguments:**

    - `amplitudes`: complex amplitude (and phase) of each source.
    - `positions_mm`: ``(x, y, z)`` of each source (mm), ``z > 0`` in front of the plane.
    - `grid`: the base plane's samples (centre pixel on the axis).
    - `wavelength_nm`: wavelength (nm).
    - `chunk`: sources evaluated at once (memory ``chunk * n^2``); the sum runs by
      `lax.scan` over chunks.

    **Returns:** the field ``(n, n)``, rows along y.

    **Example:**

    ```python
    with jax.enable_x64(True):
        u = spherical_wave_sum(jnp.ones(1), jnp.array([[0.0, 0.0, 1e3]]), grid, 550.0)
    ```
    """
    if not isinstance(chunk, int) or chunk < 1:
        raise ConfigError(f"chunk must be an integer >= 1, got {chunk!r}")
    a = jnp.asarray(amplitudes)
    a = a.astype(jnp.result_type(a.dtype, jnp.complex64))
    p = jnp.asarray(positions_mm, dtype=jnp.finfo(a.dtype).dtype)
    s = a.shape[0]
    n_chunks = -(-s // chunk)
    pad = n_chunks * chunk - s
    # Padding sources have zero amplitude and a harmless position (1 mm in front).
    a = jnp.pad(a, (0, pad)).reshape(n_chunks, chunk)
    p = jnp.pad(p, ((0, pad), (0, 0)), constant_values=1.0).reshape(n_chunks, chunk, 3)
    y, x = grid.mesh_mm()
    k = 2.0 * math.pi / nm_to_mm(wavelength_nm)

    def add(acc, block):
        amp, pos = block
        dx = x[None] - pos[:, 0, None, None]
        dy = y[None] - pos[:, 1, None, None]
        r = jnp.sqrt(dx * dx + dy * dy + pos[:, 2, None, None] ** 2)
        return acc + jnp.sum(amp[:, None, None] * jnp.exp(1j * k * r) / r, axis=0), None

    out, _ = jax.lax.scan(add, jnp.zeros(x.shape, a.dtype), (a, p))
    return out


def plane_wave_sum(bins: Complex[Array, "*b n n"]) -> Complex[Array, "*b n n"]:
    """``sum_k C_k exp(+i 2 pi k . m / N)`` at every sample ``m``: the inverse DFT, unscaled.

    `bins` are in FFT order (bin 0 first); so is the returned field (sample 0 on the
    axis). Bin ``k`` is the plane wave of spatial frequency ``k / (N pitch)``.
    """
    return jnp.fft.ifft2(bins, norm="forward")


def fresnel_base_field(
    bins_by_layer: Complex[Array, "l n n"],
    vergences_per_mm: Float[ArrayLike, " l"],
    grid: ApertureGrid,
    wavelength_nm: ArrayLike,
) -> Complex[Array, "n n"]:
    """The fast base layer: ``sum_l chirp(V_l) * plane_wave_sum(C_l)``, FFT order.

    `bins_by_layer[l]` holds the complex amplitudes of the sources of vergence layer
    ``l`` at their bins (each already carrying its own phase and ``1 / z``), the chirp is
    ``exp(i pi V_l r^2 / lambda)``. See the module docstring for what it approximates.
    """
    from invglare.optics.holographic.layers import vergence_chirp

    v = jnp.asarray(vergences_per_mm)
    chirps = jax.vmap(lambda vl: jnp.fft.ifftshift(vergence_chirp(grid, wavelength_nm, vl)))(v)
    return jnp.sum(chirps * plane_wave_sum(bins_by_layer), axis=0)
