"""Near-field (Fresnel) propagation.

Two methods, for two jobs:

* **single FFT with the quadratic phase** (Ritschel et al. 2009, eq. 3): the field
  at distance ``d`` behind the aperture is the Fourier transform of the aperture
  times ``E = exp(i pi (x^2 + y^2) / (lambda d))``, evaluated at ``x_i / (lambda d)``.
  It is the far-field machinery of :mod:`.fraunhofer` applied to ``t * E``, so its
  PSFs carry the same unit-energy normalisation and are indexed by the angle
  ``theta = x_i / d``. The phase ``E`` is only sampled well while its local
  frequency ``r / (lambda d)`` stays under the grid's Nyquist limit; see
  :func:`fresnel_chirp_aliased`.
* **near field on the image plane** (:func:`fresnel_near_field`): the same eq. 3 as
  a convolution with the Fresnel kernel (transfer function ``exp(-i pi lambda d f^2)``),
  whose sampling condition ``M p^2 >= lambda d`` holds at short distances (the eye's
  17-24 mm) where ``E`` would need thousands of samples;
* **angular spectrum** between parallel planes (same grid in and out), with the
  exact transfer function or its paraxial (Fresnel) form. The constant phase
  ``exp(i k d)`` common to every plane wave is dropped: it does not change
  intensities and would cost float32 all its phase precision.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Complex, Float, Inexact

from invglare._core.grids import AngularGrid, ApertureGrid, nm_to_mm, rad_to_deg
from invglare.optics.fourier import crop_centred, pad_centred
from invglare.optics.fraunhofer import (
    abs2,
    fraunhofer_mft,
    intensity_fft,
    open_area_px,
    power_px,
    transmitted_power,
)

TRANSFER_FUNCTIONS = ("exact", "fresnel")


def fresnel_phase(
    grid: ApertureGrid, wavelength_nm: ArrayLike, distance_mm: ArrayLike
) -> Complex[Array, "n n"]:
    """The quadratic phase ``E = exp(i pi r^2 / (lambda d))`` on the aperture grid."""
    y, x = grid.mesh_mm()
    return jnp.exp(1j * jnp.pi * (x**2 + y**2) / (nm_to_mm(wavelength_nm) * distance_mm))


def fresnel_chirp_aliased(
    grid: ApertureGrid, wavelength_nm: float, distance_mm: float, radius_mm: float
) -> bool:
    """Whether ``E`` aliases inside `radius_mm`: its local frequency there exceeds Nyquist."""
    local_freq = radius_mm / (wavelength_nm * 1e-6 * distance_mm)
    return bool(local_freq > float(grid.max_frequency_per_mm()))


def fresnel_number(half_width_mm: float, wavelength_nm: float, distance_mm: float) -> float:
    """``a^2 / (lambda d)``: far below 1 the Fraunhofer limit holds, far above it, geometry."""
    return half_width_mm**2 / (wavelength_nm * 1e-6 * distance_mm)


def fresnel_fft(
    field: Inexact[Array, "n n"],
    grid: ApertureGrid,
    wavelength_nm: ArrayLike,
    distance_mm: ArrayLike,
    fft_npix: int,
    out_npix: int | None = None,
) -> tuple[Float[Array, "out out"], Float[Array, ""]]:
    """Fresnel PSF at `distance_mm` by one FFT (eq. 3), with its angular pixel scale (deg).

    On the image plane a pixel is ``distance * pixel_scale`` wide.
    """
    # The phase leaves the power through the aperture as it is: measured on `field`.
    psf = intensity_fft(
        field * fresnel_phase(grid, wavelength_nm, distance_mm), fft_npix, out_npix,
        open_area_px=open_area_px(field),
    )  # fmt: skip
    scale_deg = rad_to_deg(nm_to_mm(wavelength_nm) / (fft_npix * grid.pitch_mm))
    return psf, scale_deg


def fresnel_mft(
    field: Inexact[Array, "n n"],
    grid: ApertureGrid,
    wavelength_nm: ArrayLike,
    distance_mm: ArrayLike,
    output: AngularGrid,
) -> Float[Array, "out out"]:
    """Fresnel PSF (eq. 3) at any output sampling, by matrix Fourier transform."""
    return fraunhofer_mft(
        field * fresnel_phase(grid, wavelength_nm, distance_mm), grid, wavelength_nm, output,
        open_area_mm2=transmitted_power(field, grid.pitch_mm),
    )  # fmt: skip


def near_field_fft_npix(
    grid: ApertureGrid, wavelength_nm: float, distance_mm: float, out_npix: int
) -> int:
    """The padded size for :func:`fresnel_near_field`: its transfer function sampled, no wrap.

    The paraxial transfer function ``exp(-i pi lambda d f^2)`` is sampled without
    aliasing on ``M`` samples of pitch ``p`` when ``M p^2 >= lambda d`` (its phase then
    changes by at most pi between frequency samples); ``M >= 2 n`` keeps the light that
    leaves the window from wrapping round, and ``M >= out_npix`` holds the output. Even.
    """
    pitch = float(grid.pitch_mm)
    chirp = math.ceil(float(wavelength_nm) * 1e-6 * float(distance_mm) / pitch**2)
    m = max(2 * grid.npix, int(out_npix), chirp)
    return m + m % 2


def fresnel_near_field(
    field: Inexact[Array, "n n"],
    grid: ApertureGrid,
    wavelength_nm: ArrayLike,
    distance_mm: ArrayLike,
    fft_npix: int,
    out_npix: int | None = None,
    *,
    open_area_mm2: ArrayLike | None = None,
) -> Float[Array, "out out"]:
    """Eq. 3 at a short distance, without aliasing: the Fresnel pattern on the image plane.

    ``|F{P E}(x / (lambda d))|^2`` with ``E = exp(i pi r^2 / (lambda d))`` is, up to
    ``(lambda d)^2``, ``|(P * h)(x)|^2`` with the Fresnel kernel
    ``h = exp(i pi r^2 / (lambda d))``: the aperture convolved with the kernel, computed
    as ``F^-1{F{P} exp(-i pi lambda d f^2)}`` on the aperture grid padded to `fft_npix`
    samples (:func:`near_field_fft_npix` chooses one that samples the transfer function).
    Where the single-FFT form needs ``E`` resolved by the raster (thousands of samples at
    the eye's 17-24 mm), this one needs ``M p^2 >= lambda d``: a few samples there.

    The output is on the image plane at the aperture's pitch, ``x_k = (k - out // 2) p``,
    i.e. at angles ``x / d``: pixels of ``p / d`` rad. Per pixel, the fraction of the power
    through the aperture (`open_area_mm2` if given, else the raster's ``sum |t| p^2``), the
    normalisation of :mod:`invglare.optics.fraunhofer`: the padded plane holds the raster's
    ``sum |t|^2 / sum |t|`` of it (the transfer function has modulus 1).
    """
    n = field.shape[-1]
    out_npix = fft_npix if out_npix is None else out_npix
    if fft_npix < max(n, out_npix):
        raise ValueError(f"fft_npix ({fft_npix}) must hold the field ({n}) and output ({out_npix})")
    padded = pad_centred(field.astype(jnp.result_type(field.dtype, jnp.complex64)), fft_npix)
    freqs = jnp.fft.fftfreq(fft_npix, d=grid.pitch_mm).astype(jnp.real(padded).dtype)
    h = transfer_function(freqs, freqs, wavelength_nm, distance_mm, "fresnel")
    out = jnp.fft.ifft2(jnp.fft.fft2(padded) * h)
    power = power_px(field, open_area_mm2, grid.pitch_mm)
    return crop_centred(abs2(out), out_npix) / power


def transfer_function(
    freqs_y_per_mm: Float[Array, " m"],
    freqs_x_per_mm: Float[Array, " m"],
    wavelength_nm: ArrayLike,
    distance_mm: ArrayLike,
    kind: str = "exact",
) -> Complex[Array, "m m"]:
    """Free-space transfer function between parallel planes, without the constant ``e^{ikd}``.

    ``exact``: ``exp(i 2 pi d (sqrt(1/lambda^2 - f^2) - 1/lambda))``, evanescent waves
    decaying; ``fresnel``: ``exp(-i pi lambda d f^2)``.
    """
    lam = nm_to_mm(wavelength_nm)
    f2 = freqs_y_per_mm[:, None] ** 2 + freqs_x_per_mm[None, :] ** 2
    if kind == "fresnel":
        return jnp.exp(-1j * jnp.pi * lam * distance_mm * f2)
    if kind != "exact":
        raise ValueError(
            f"transfer function {kind!r} unknown; expected one of {TRANSFER_FUNCTIONS}"
        )
    k2 = 1.0 / lam**2
    kz = jnp.sqrt(jnp.maximum(k2 - f2, 0.0))
    # sqrt(k^2 - f^2) - k written without cancellation, so float32 keeps the phase.
    propagating = jnp.exp(-2j * jnp.pi * distance_mm * f2 / (1.0 / lam + kz))
    decay = jnp.exp(-2 * jnp.pi * distance_mm * jnp.sqrt(jnp.maximum(f2 - k2, 0.0)))
    evanescent = decay * jnp.exp(-2j * jnp.pi * distance_mm / lam)
    return jnp.where(f2 <= k2, propagating, evanescent)


def angular_spectrum_kernel(
    grid: ApertureGrid,
    wavelength_nm: ArrayLike,
    distance_mm: ArrayLike,
    pad_npix: int | None = None,
    kind: str = "exact",
    band_limit: bool = True,
) -> Complex[Array, "m m"]:
    """The band-limited angular-spectrum transfer function between two planes, FFT order.

    :func:`transfer_function` on the FFT frequencies of an `m`-sample grid of the same
    pitch (`pad_npix`, default the grid itself, ``m = n``: a *periodic* propagation, exact
    for a field that is periodic on the grid and otherwise correct where light does not
    cross the window's edge on the way), with `band_limit` the frequencies whose phase the
    grid undersamples removed (Matsushima & Shimobaba 2009): the cut is at
    ``1 / (lambda sqrt((2 d / (m pitch))^2 + 1))`` per axis. Made once, it serves every
    field propagated over the same distance (:func:`angular_spectrum`, the holographic
    eye's iterations).
    """
    m = grid.npix if pad_npix is None else pad_npix
    freqs = jnp.fft.fftfreq(m, d=grid.pitch_mm)
    h = transfer_function(freqs, freqs, wavelength_nm, distance_mm, kind)
    if band_limit:
        span_mm = m * grid.pitch_mm
        f_max = 1.0 / (nm_to_mm(wavelength_nm) * jnp.sqrt((2 * distance_mm / span_mm) ** 2 + 1))
        passed = jnp.abs(freqs) <= f_max
        h = h * (passed[:, None] & passed[None, :])
    return h


def angular_spectrum(
    field: Inexact[Array, "n n"],
    grid: ApertureGrid,
    wavelength_nm: ArrayLike,
    distance_mm: ArrayLike,
    pad_npix: int | None = None,
    kind: str = "exact",
    band_limit: bool = True,
) -> Complex[Array, "n n"]:
    """Propagate a complex field by `distance_mm` on the same grid (angular spectrum method).

    The field is zero-padded to `pad_npix` (default twice its size) so that light
    leaving the window does not wrap around, then cropped back. With `band_limit`
    (default) frequencies whose transfer-function phase is undersampled by the
    padded grid are removed (Matsushima & Shimobaba 2009): they would otherwise
    alias back into the window at long distances. The cut is at
    ``1 / (lambda sqrt((2 d / (m pitch))^2 + 1))`` per axis.
    """
    n = field.shape[-1]
    m = 2 * n if pad_npix is None else pad_npix
    padded = pad_centred(field.astype(jnp.result_type(field.dtype, jnp.complex64)), m)
    h = angular_spectrum_kernel(grid, wavelength_nm, distance_mm, m, kind, band_limit)
    # Round trip through unshifted FFTs keeps every sample where it was: no shifts needed.
    out = jnp.fft.ifft2(jnp.fft.fft2(padded) * h)
    return crop_centred(out, n)
