"""Fraunhofer (far-field) propagation: intensity PSFs by FFT and by matrix Fourier transform.

**Normalisation.** Every PSF returned here holds, per output pixel, the fraction of
the power through the aperture that lands in that pixel:

    psf[k] = |U(theta_k)|^2 * (dtheta / lambda)^2 / P

with ``U`` the aperture's continuous Fourier transform at frequency
``theta / lambda``, ``dtheta`` the output pixel scale (rad) and ``P`` the power
through the aperture for unit incident intensity (mm^2): the open area of a clear
aperture. Divide by the pixel solid angle ``dtheta^2`` to get a PSF in sr^-1.

``P`` is the aperture's area in closed form where the caller knows it (a lone disk,
ellipse, polygon or capsule: `open_area_mm2`), and otherwise the raster's own
transmission ``sum |t| * d^2`` (``d`` the aperture pitch): an anti-aliased pixel of
coverage ``c`` lets ``c`` of its area through, so a sharp-edged aperture's raster
measures its area exactly (a 4 mm disk on a 256-sample raster to 4e-10), and a
sub-pixel particle of coverage ``c`` stops ``c`` of its pixel. The raster itself
diffracts only ``sum |t|^2 * d^2`` (Parseval), a little less: the difference is the
light an ideal sharp edge sends beyond the grid's Nyquist angle ``lambda / (2 d)``,
which no sampled model holds. So over an unbounded output plane (an FFT covers it)
a PSF sums to just under 1 (0.9973 for a disk 252 samples across), a finite MFT field
to its encircled fraction, and the Airy core and encircled energies match the closed
form (2e-4 at the default 256-sample raster), where normalising by the raster's own
power made them 0.27 % too high.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Inexact

from invglare._core.grids import AngularGrid, ApertureGrid, nm_to_mm, rad_to_deg
from invglare._core.maths import safe_sqrt
from invglare._core.xla import materialise
from invglare.optics.fourier import crop_centred, dft_matrix, mft2, mft2_matrices

# Guards the normalisation of an aperture that transmits nothing (e.g. a pupil of 0 mm).
_TINY_POWER = 1e-30


def abs2(z: Inexact[Array, "*shape"]) -> Float[Array, "*shape"]:
    """``|z|^2`` as ``re^2 + im^2``: `jnp.abs` takes a square root that the square undoes
    (the 512² intensity spent a fifth of its time there)."""
    return z.real**2 + z.imag**2 if jnp.iscomplexobj(z) else z**2


def open_area_px(field: Inexact[Array, "n n"]) -> Float[Array, ""]:
    """The raster's transmission ``sum |t|``: the open area in aperture pixels.

    A complex field's modulus is taken with a square root that has a finite derivative
    where the field is 0 (most of the window).
    """
    if not jnp.iscomplexobj(field):
        return jnp.sum(jnp.abs(field))
    return jnp.sum(safe_sqrt(abs2(field)))


def transmitted_power(field: Inexact[Array, "n n"], pitch_mm: ArrayLike) -> Float[Array, ""]:
    """Power through the aperture, ``sum |t| * pitch^2`` (mm^2 for unit incident intensity).

    The normalisation of every PSF here (see the module docstring): the raster's open area.
    """
    return open_area_px(field) * jnp.asarray(pitch_mm) ** 2


def power_px(
    field: Inexact[Array, "n n"], open_area_mm2: ArrayLike | None, pitch_mm: ArrayLike
) -> Float[Array, ""]:
    """``P / d^2``, a PSF's divisor: a closed-form area when given, else the raster's
    transmission; never 0."""
    if open_area_mm2 is None:
        power = open_area_px(field)
    else:
        power = jnp.asarray(open_area_mm2) / jnp.asarray(pitch_mm) ** 2
    return jnp.maximum(power, _TINY_POWER)


def _checkerboard(n: int, dtype) -> Float[Array, "n n"]:
    """(-1)^(row + col): modulating the input by it moves the DFT's origin to index m // 2."""
    sign = 1 - 2 * (jnp.arange(n) % 2)
    return (sign[:, None] * sign[None, :]).astype(dtype)


def _hermitian_full(half: Float[Array, "m h"], m: int) -> Float[Array, "m m"]:
    """Rebuild the full ``|X|^2`` of a real input from its rfft half (``X[-k] = conj X[k]``)."""
    mirrored = jnp.roll(jnp.flip(half, axis=0), 1, axis=0)
    return jnp.concatenate([half, mirrored[:, 1 : m // 2][:, ::-1]], axis=1)


def intensity_fft(
    field: Inexact[Array, "n n"],
    fft_npix: int,
    out_npix: int | None = None,
    *,
    open_area_px: ArrayLike | None = None,
) -> Float[Array, "out out"]:
    """Far-field intensity of `field` zero-padded to `fft_npix` samples, per unit power.

    Normalised by the power through the aperture: `open_area_px` (its area in aperture
    pixels, ``area / pitch^2``) when given, else the raster's transmission ``sum |t|``
    (see the module docstring). The output's origin is at index ``out_npix // 2``. The
    field's position inside its window only adds a linear phase, which the intensity
    ignores, so no input shift is needed; the output shift is folded into the input as a
    checkerboard sign (even sizes), and a real field uses the half-size real FFT.
    """
    n = field.shape[-1]
    out_npix = fft_npix if out_npix is None else out_npix
    if fft_npix < n:
        raise ValueError(f"fft_npix ({fft_npix}) must be at least the aperture npix ({n})")
    if out_npix > fft_npix:
        raise ValueError(f"out_npix ({out_npix}) must not exceed fft_npix ({fft_npix})")
    if fft_npix > n:
        field = materialise(field)
    norm = power_px(field, open_area_px, 1.0) * fft_npix**2
    if fft_npix % 2 == 0:
        real_dtype = jnp.real(field).dtype
        modulated = field * _checkerboard(n, real_dtype)
        if jnp.iscomplexobj(field):
            spectrum = jnp.fft.fft2(modulated, s=(fft_npix, fft_npix))
            full = abs2(spectrum) / norm
        else:
            # Normalised before the mirror: the gradient's sum over the output for the
            # normalisation then runs over the half plane (a 10 % faster 512² gradient).
            # The half is put in memory first: fused into the mirror, the squared modulus
            # was computed element by element in reverse order (0.5 ms of a 1.9 ms 512² PSF).
            half = jnp.fft.rfft2(modulated, s=(fft_npix, fft_npix))
            full = _hermitian_full(materialise(abs2(half) / norm), fft_npix)
    else:
        spectrum = jnp.fft.fftshift(jnp.fft.fft2(field, s=(fft_npix, fft_npix)))
        full = abs2(spectrum) / norm
    return crop_centred(full, out_npix)


def fraunhofer_fft(
    field: Inexact[Array, "n n"],
    grid: ApertureGrid,
    wavelength_nm: ArrayLike,
    fft_npix: int,
    out_npix: int | None = None,
    *,
    open_area_mm2: ArrayLike | None = None,
) -> tuple[Float[Array, "out out"], Float[Array, ""]]:
    """Far-field PSF by zero-padded FFT, returned with its pixel scale in degrees.

    The pixel scale is fixed by the sampling: ``wavelength / (fft_npix * pitch)`` rad.
    `open_area_mm2`: the aperture's area in closed form, if known (module docstring).
    """
    scale_deg = rad_to_deg(nm_to_mm(wavelength_nm) / (fft_npix * grid.pitch_mm))
    area_px = None if open_area_mm2 is None else jnp.asarray(open_area_mm2) / grid.pitch_mm**2
    return intensity_fft(field, fft_npix, out_npix, open_area_px=area_px), scale_deg


def fraunhofer_mft(
    field: Inexact[Array, "n n"],
    grid: ApertureGrid,
    wavelength_nm: ArrayLike,
    output: AngularGrid,
    *,
    open_area_mm2: ArrayLike | None = None,
) -> Float[Array, "out out"]:
    """Far-field PSF by matrix Fourier transform at any output pixel scale and field of view.

    `open_area_mm2`: the aperture's area in closed form, if known (module docstring).
    """
    lam_mm = nm_to_mm(wavelength_nm)
    if jnp.iscomplexobj(field):
        freqs = output.coords_rad() / lam_mm
        intensity = abs2(mft2(field, grid.coords_mm(), freqs, freqs))
    else:
        intensity = _real_field_intensity(
            field, grid.coords_mm(), output.pixel_scale_rad / lam_mm, output.npix
        )
    power = power_px(field, open_area_mm2, grid.pitch_mm)
    # |pitch^2 * DFT|^2 * (dtheta / lambda)^2 / (power * pitch^2)
    scale = (grid.pitch_mm * output.pixel_scale_rad / lam_mm) ** 2
    return intensity * (scale / power)


def _real_field_intensity(
    field: Float[Array, "n n"], coords_mm: Float[Array, " n"], dfreq: ArrayLike, npix: int
) -> Float[Array, "npix npix"]:
    """``|MFT|²`` of a real field on the centred ``npix`` grid of step `dfreq`, from one half.

    A real field's transform is Hermitian, ``F(-f) = conj(F(f))``, so its intensity is
    point-symmetric about zero frequency. Rows ``fy = 0 .. h`` steps (``h = npix // 2``;
    for an even size one row beyond the grid) over columns ``-h .. h`` are computed, and
    the rows below zero are that block turned by 180°: the second (complex) product, most
    of the cost, shrinks to about half.
    """
    h = npix // 2
    a_x = dft_matrix(coords_mm, (jnp.arange(2 * h + 1) - h) * dfreq)
    # The rows fy = 0 .. h are the columns' matrix from its middle on: its exponentials,
    # a good part of the cost, are computed once.
    block = abs2(mft2_matrices(field, a_x[h:], a_x))
    turned = block[::-1, ::-1]
    return jnp.concatenate([turned[:h, :npix], block[: npix - h, :npix]], axis=0)
