"""Fraunhofer (far-field) propagation: intensity PSFs by FFT and by matrix Fourier transform.

**Normalisation.** Every PSF returned here holds, per output pixel, the fraction of
the power transmitted by the aperture that lands in that pixel:

    psf[k] = |U(theta_k)|^2 * (dtheta / lambda)^2 / (sum |t|^2 * d^2)

with ``U`` the aperture's continuous Fourier transform at frequency
``theta / lambda``, ``dtheta`` the output pixel scale (rad) and ``d`` the aperture
pitch. By Parseval the sum over an unbounded output plane is exactly 1 (an FFT
covers that whole plane); a finite MFT field holds the encircled fraction.
Divide by the pixel solid angle ``dtheta^2`` to get a PSF in sr^-1.

The power is that of the *raster*, ``sum |t|^2``: an anti-aliased edge pixel of
coverage ``c`` transmits amplitude ``c`` but counts ``c^2``. The difference from
the geometric area is the light an ideal sharp edge diffracts beyond the grid's
Nyquist angle ``lambda / (2 pitch)``, which no sampled model represents; it
shrinks as the raster gets finer (0.5 % for a pupil 128 px across).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Inexact

from invglare._core.grids import AngularGrid, ApertureGrid, nm_to_mm, rad_to_deg
from invglare._core.xla import materialise
from invglare.optics.fourier import crop_centred, dft_matrix, mft2, mft2_matrices

# Guards the normalisation of an aperture that transmits nothing (e.g. a pupil of 0 mm).
_TINY_POWER = 1e-30


def abs2(z: Inexact[Array, "*shape"]) -> Float[Array, "*shape"]:
    """``|z|^2`` as ``re^2 + im^2``: `jnp.abs` takes a square root that the square undoes
    (the 512² intensity spent a fifth of its time there)."""
    return z.real**2 + z.imag**2 if jnp.iscomplexobj(z) else z**2


def transmitted_power(field: Inexact[Array, "n n"], pitch_mm: ArrayLike) -> Float[Array, ""]:
    """Power through the aperture, ``sum |t|^2 * pitch^2`` (mm^2 for unit incident intensity)."""
    return jnp.sum(abs2(field)) * jnp.asarray(pitch_mm) ** 2


def _checkerboard(n: int, dtype) -> Float[Array, "n n"]:
    """(-1)^(row + col): modulating the input by it moves the DFT's origin to index m // 2."""
    sign = 1 - 2 * (jnp.arange(n) % 2)
    return (sign[:, None] * sign[None, :]).astype(dtype)


def _hermitian_full(half: Float[Array, "m h"], m: int) -> Float[Array, "m m"]:
    """Rebuild the full ``|X|^2`` of a real input from its rfft half (``X[-k] = conj X[k]``)."""
    mirrored = jnp.roll(jnp.flip(half, axis=0), 1, axis=0)
    return jnp.concatenate([half, mirrored[:, 1 : m // 2][:, ::-1]], axis=1)


def intensity_fft(
    field: Inexact[Array, "n n"], fft_npix: int, out_npix: int | None = None
) -> Float[Array, "out out"]:
    """Unit-energy far-field intensity of `field` zero-padded to `fft_npix` samples.

    The output's origin is at index ``out_npix // 2``. The field's position inside
    its window only adds a linear phase, which the intensity ignores, so no input
    shift is needed; the output shift is folded into the input as a checkerboard
    sign (even sizes), and a real field uses the half-size real FFT.
    """
    n = field.shape[-1]
    out_npix = fft_npix if out_npix is None else out_npix
    if fft_npix < n:
        raise ValueError(f"fft_npix ({fft_npix}) must be at least the aperture npix ({n})")
    if out_npix > fft_npix:
        raise ValueError(f"out_npix ({out_npix}) must not exceed fft_npix ({fft_npix})")
    if fft_npix > n:
        field = materialise(field)
    norm = jnp.maximum(jnp.sum(abs2(field)), _TINY_POWER) * fft_npix**2
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
) -> tuple[Float[Array, "out out"], Float[Array, ""]]:
    """Far-field PSF by zero-padded FFT, returned with its pixel scale in degrees.

    The pixel scale is fixed by the sampling: ``wavelength / (fft_npix * pitch)`` rad.
    """
    scale_deg = rad_to_deg(nm_to_mm(wavelength_nm) / (fft_npix * grid.pitch_mm))
    return intensity_fft(field, fft_npix, out_npix), scale_deg


def fraunhofer_mft(
    field: Inexact[Array, "n n"],
    grid: ApertureGrid,
    wavelength_nm: ArrayLike,
    output: AngularGrid,
) -> Float[Array, "out out"]:
    """Far-field PSF by matrix Fourier transform at any output pixel scale and field of view."""
    lam_mm = nm_to_mm(wavelength_nm)
    if jnp.iscomplexobj(field):
        freqs = output.coords_rad() / lam_mm
        intensity = abs2(mft2(field, grid.coords_mm(), freqs, freqs))
    else:
        intensity = _real_field_intensity(
            field, grid.coords_mm(), output.pixel_scale_rad / lam_mm, output.npix
        )
    power = jnp.maximum(jnp.sum(abs2(field)), _TINY_POWER)
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
