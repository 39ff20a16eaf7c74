"""Discrete Fourier transforms on centred grids: FFT helpers and the matrix Fourier transform.

All transforms follow the centring convention of :mod:`invglare._core.grids`:
index ``n // 2`` is the origin on both the input and the output grid. With that
convention the FFT of a field zero-padded to ``m`` samples and the matrix Fourier
transform (MFT) evaluated at frequencies ``(k - m // 2) / (m * pitch)`` are the
same exact DFT.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Complex, Float, Inexact


def fft_size(n: int, *, even: bool = False) -> int:
    """The smallest integer >= `n` (even, with `even`) whose only prime factors are 2, 3, 5.

    Such sizes are fast for every FFT library JAX uses (pocketfft/ducc on CPU,
    cuFFT on GPU), while costing at most a few percent more samples than `n`.

    ```python
    fft_size(1025)              # 1080
    fft_size(243, even=True)    # 250
    ```
    """
    if n < 1:
        raise ValueError(f"FFT size must be >= 1, got {n}")
    step = 2 if even else 1
    m = max(2, n + n % 2) if even else n
    while True:  # at most a few percent above n, so a plain search is cheap
        k = m
        for p in (2, 3, 5):
            while k % p == 0:
                k //= p
        if k == 1:
            return m
        m += step


def pad_centred(field: Inexact[Array, "n n"], m: int) -> Inexact[Array, "m m"]:
    """Zero-pad a square array to ``m`` x ``m`` keeping its centre pixel at ``m // 2``."""
    n = field.shape[-1]
    if m < n:
        raise ValueError(f"cannot pad a {n}-pixel field to {m} pixels")
    before = m // 2 - n // 2
    after = m - n - before
    pad = [(0, 0)] * (field.ndim - 2) + [(before, after), (before, after)]
    return jnp.pad(field, pad)


def crop_centred(arr: Inexact[Array, "m m"], n: int) -> Inexact[Array, "n n"]:
    """Crop a square array to ``n`` x ``n`` around its centre pixel (inverse of pad_centred)."""
    m = arr.shape[-1]
    if n > m:
        raise ValueError(f"cannot crop a {m}-pixel array to {n} pixels")
    start = m // 2 - n // 2
    return arr[..., start : start + n, start : start + n]


def centred_fft2(field: Inexact[Array, "m m"]) -> Complex[Array, "m m"]:
    """DFT with the origin at index ``m // 2`` on input and output (no pitch factor)."""
    return jnp.fft.fftshift(jnp.fft.fft2(jnp.fft.ifftshift(field, axes=(-2, -1))), axes=(-2, -1))


def dft_matrix(
    coords_mm: Float[Array, " n_in"], freqs_per_mm: Float[Array, " n_out"]
) -> Complex[Array, "n_out n_in"]:
    """Matrix of ``exp(-2 pi i f_k x_n)``: one axis of the matrix Fourier transform."""
    return jnp.exp(-2j * jnp.pi * freqs_per_mm[:, None] * coords_mm[None, :])


def mft2(
    field: Inexact[Array, "n n"],
    coords_mm: Float[Array, " n"],
    freqs_y_per_mm: Float[Array, " ny"],
    freqs_x_per_mm: Float[Array, " nx"],
) -> Complex[Array, "ny nx"]:
    """Matrix Fourier transform: the exact DFT of `field` at arbitrary output frequencies.

    Returns ``sum_{m,n} field[m, n] exp(-2 pi i (fy x_m + fx x_n))`` (no pitch factor).
    Cost is ``O(n^2 (nx + ny))``, so it beats the FFT when the output is small or
    must be finer than the FFT's native sampling.
    """
    a_y = dft_matrix(coords_mm, freqs_y_per_mm)
    a_x = dft_matrix(coords_mm, freqs_x_per_mm)
    return mft2_matrices(field, a_y, a_x)


def mft2_matrices(
    field: Inexact[Array, "n n"], a_y: Complex[Array, "ny n"], a_x: Complex[Array, "nx n"]
) -> Complex[Array, "ny nx"]:
    """:func:`mft2` with its two :func:`dft_matrix` factors given: ``a_y @ field @ a_x.T``."""
    if jnp.iscomplexobj(field):
        inner = field @ a_x.T
    else:
        # A real field needs two real products instead of one complex one.
        inner = (field @ a_x.real.T) + 1j * (field @ a_x.imag.T)
    return a_y @ inner
