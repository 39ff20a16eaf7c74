"""Wide-angle scatter of small opaque particles, in closed form, beyond what a raster holds.

A raster of pitch ``p`` carries light only up to ``lambda / (2 p)`` rad; a particle of
radius ``a`` well below the pitch (a cornea cell, ``a`` = 7.5 um) diffracts to
``~ lambda / a``, several degrees. By Babinet's principle an opaque disk in a lit pupil
takes away the field of a disk-shaped hole: its far-field amplitude is
``A_k(f) = w_k t_k pi a_k^2 jinc(2 pi a_k |f|) exp(-2 pi i f . x_k)`` (``w_k`` its opacity,
``t_k`` the amplitude of the light reaching it, ``x_k`` its centre), and its scattered
power is its blocked power ``pi a_k^2`` (for ``w t = 1``), spread as an Airy pattern of
diameter ``2 a_k``. Beyond the pupil's own diffraction core the field of many particles is

- ``"phases"``: ``|sum_k A_k(f)|^2``, the particles' interference with their positions'
  phases (speckle, as one eye has it);
- ``"ensemble"``: ``sum_k |A_k(f)|^2``, its average over the particles' positions (the
  cross terms average to zero away from the core): smooth, and the same for every draw,
  what a fit of structure it cannot resolve uses.

:func:`particle_scatter` gives either, per pixel of an angular grid, in the
normalisation of :mod:`invglare.optics.fraunhofer` (the fraction of the transmitted
power ``P`` per pixel): ``|A(f)|^2 (dtheta / lambda)^2 / P``.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, ArrayLike, Float

from invglare._core.checks import choose
from invglare._core.grids import AngularGrid, nm_to_mm
from invglare.optics.bessel import jinc

__all__ = ["SCATTER_METHODS", "disk_amplitude_mm2", "particle_scatter"]

#: How the particles' fields combine: with their positions' phases, or on average.
SCATTER_METHODS = ("ensemble", "phases")


def disk_amplitude_mm2(
    radius_mm: Float[ArrayLike, "*shape"], frequency_per_mm: Float[ArrayLike, "*shape"]
) -> Float[Array, "*shape"]:
    """Far-field amplitude (mm^2) of a disk-shaped hole of radius ``a``: ``pi a^2 jinc(2 pi a f)``.

    Its square integrates over the plane of frequencies to ``pi a^2`` (Parseval).
    """
    a = jnp.asarray(radius_mm)
    return math.pi * a * a * jinc(2.0 * math.pi * a * jnp.asarray(frequency_per_mm))


def particle_scatter(
    radii_mm: Float[ArrayLike, " k"],
    amplitudes: Float[ArrayLike, " k"],
    centres_mm: Float[ArrayLike, "k 2"],
    output: AngularGrid,
    wavelength_nm: Float[ArrayLike, ""],
    power_mm2: Float[ArrayLike, ""],
    method: str = "ensemble",
) -> Float[Array, "npix npix"]:
    """Scatter of opaque disks on `output`, fraction of `power_mm2` per pixel.

    **Arguments:**

    - `radii_mm`: ``(k,)`` particle radii (mm).
    - `amplitudes`: ``(k,)`` each particle's ``w_k t_k``: its opacity (a relaxed count's
      weight) times the amplitude of the light that reaches it (0 outside the pupil or
      behind a lash, 1 in the open pupil).
    - `centres_mm`: ``(k, 2)`` centres (x, y) in the pupil plane (``"phases"`` only).
    - `output`: the angular grid (its centre pixel on the axis).
    - `wavelength_nm`: the wavelength.
    - `power_mm2`: the power the pupil transmits (mm^2), the normalisation's ``P``.
    - `method`: ``"ensemble"`` (default) or ``"phases"``.

    **Returns:** ``(npix, npix)``; over the whole plane the ensemble sums to
    ``sum_k (w_k t_k)^2 pi a_k^2 / P`` (Babinet), the part beyond the grid's field lost.

    **Example:**

    ```python
    veil = particle_scatter(r, w, xy, AngularGrid(256, 0.02), 550.0, 7.0)
    ```
    """
    choose("method", method, SCATTER_METHODS)
    radii = jnp.asarray(radii_mm)
    amps = jnp.asarray(amplitudes, radii.dtype)
    lam = nm_to_mm(jnp.asarray(wavelength_nm, radii.dtype))
    coords = output.coords_rad().astype(radii.dtype) / lam  # frequencies (1/mm)
    scale = (output.pixel_scale_rad.astype(radii.dtype) / lam) ** 2 / jnp.asarray(power_mm2)
    if method == "ensemble":
        # Accumulated particle by particle: no (k, npix, npix) array.
        f = jnp.hypot(coords[:, None], coords[None, :])

        def one(acc, rk_ak):
            rk, ak = rk_ak
            return acc + (ak * disk_amplitude_mm2(rk, f)) ** 2, None

        total, _ = lax.scan(one, jnp.zeros_like(f), (radii, amps))
        return total * scale
    centres = jnp.asarray(centres_mm, radii.dtype)
    # Separable phases: exp(-2 pi i (fx x + fy y)) = row phase x column phase.
    phase_x = jnp.exp(-2j * math.pi * coords[None, :] * centres[:, 0:1])  # (k, npix)
    phase_y = jnp.exp(-2j * math.pi * coords[None, :] * centres[:, 1:2])
    f = jnp.hypot(coords[:, None], coords[None, :])

    def one_phased(acc, item):
        rk, ak, px, py = item
        return acc + (ak * disk_amplitude_mm2(rk, f)) * (py[:, None] * px[None, :]), None

    field, _ = lax.scan(
        one_phased,
        jnp.zeros(f.shape, phase_x.dtype),
        (radii, amps, phase_x, phase_y),
    )
    return (field.real**2 + field.imag**2) * scale
