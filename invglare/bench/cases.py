"""Benchmark cases: each builds, for a size N, a zero-argument callable to time.

*Floor* cases time a bare 2D FFT of an N x N complex64 array, the least work any
N x N diffraction pipeline must do; *pipeline* cases are compared with the
fastest floor measured in the same run. Later models add their cases to
:data:`CASES`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Case:
    name: str
    kind: str  # "floor" or "pipeline"
    description: str
    make: Callable[[int], Callable[[], object] | None]  # None: not available here
    forward: str | None = None  # for a gradient case: the case it differentiates


def _random_complex(n: int) -> np.ndarray:
    rng = np.random.default_rng(0)
    return (rng.standard_normal((n, n)) + 1j * rng.standard_normal((n, n))).astype(np.complex64)


def _scipy_fft(n: int):
    import scipy.fft

    x = _random_complex(n)
    return lambda: scipy.fft.fft2(x, workers=2)


def _pyfftw_fft(n: int):
    try:
        import pyfftw
    except ImportError:
        return None
    a = pyfftw.empty_aligned((n, n), dtype="complex64")
    a[:] = _random_complex(n)
    plan = pyfftw.builders.fft2(a, threads=2, planner_effort="FFTW_MEASURE")
    return plan


def _jax_fft(n: int):
    import jax
    import jax.numpy as jnp

    x = jnp.asarray(_random_complex(n))
    fft = jax.jit(jnp.fft.fft2)
    return lambda: fft(x)


def _disk_model(n: int):
    """A 4 mm pupil on an N/2 raster, FFT to N x N: the monochrome PSF fast path."""
    from invglare.aperture import Aperture, Disk
    from invglare.models.aperture_psf import AperturePSF

    return AperturePSF.build(
        Aperture((Disk(4.0),)),
        focal_length_mm=17.0,
        wavelengths_nm=550.0,
        npix=n,
        aperture_npix=n // 2,
    )


def _psf_forward(n: int):
    import jax

    model = _disk_model(n)
    forward = jax.jit(lambda m: m())
    return lambda: forward(model)


def _psf_gradient(n: int):
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    model = _disk_model(n)
    weights = jnp.asarray(np.random.default_rng(1).random((n, n)), jnp.float32)

    def loss(diameter, m):
        m = eqx.tree_at(lambda m: m.aperture.shapes[0].diameter_mm, m, diameter)
        return jnp.sum(m() * weights)

    grad = jax.jit(jax.grad(loss))
    d0 = jnp.float32(4.0)
    return lambda: grad(d0, model)


def _convolve_setup(n: int):
    """An N x N RGB frame and an (N/4 + 1)^2 RGB PSF."""
    import jax.numpy as jnp

    rng = np.random.default_rng(2)
    image = jnp.asarray(rng.random((n, n, 3)) * 10, jnp.float32)
    psf = rng.random((n // 4 + 1, n // 4 + 1, 3))
    return image, jnp.asarray(psf / psf.sum(axis=(0, 1)), jnp.float32)


def _convolve_forward(n: int):
    import jax

    from invglare.render.convolve import convolve_psf

    image, psf = _convolve_setup(n)
    run = jax.jit(convolve_psf)
    return lambda: run(image, psf)


def _convolve_gradient(n: int):
    import jax
    import jax.numpy as jnp

    from invglare.render.convolve import convolve_psf

    image, psf = _convolve_setup(n)
    grad = jax.jit(jax.grad(lambda p: jnp.sum(jnp.sqrt(convolve_psf(image, p) + 1.0))))
    return lambda: grad(psf)


CASES: tuple[Case, ...] = (
    Case("fft_floor_scipy", "floor", "scipy.fft.fft2, complex64, 2 workers", _scipy_fft),
    Case("fft_floor_pyfftw", "floor", "pyfftw fft2, complex64, 2 threads", _pyfftw_fft),
    Case("fft_jax", "pipeline", "bare jnp.fft.fft2, complex64 (JAX's own FFT)", _jax_fft),
    Case(
        "psf_mono",
        "pipeline",
        "disk raster (N/2) + real FFT to N + squared modulus + normalise, jitted",
        _psf_forward,
    ),
    Case(
        "psf_mono_grad",
        "pipeline",
        "d(sum w * PSF)/d(diameter) of psf_mono",
        _psf_gradient,
        forward="psf_mono",
    ),
    Case(
        "convolve_rgb",
        "pipeline",
        "FFT convolution of an N x N RGB frame with an (N/4+1)^2 RGB PSF, padded",
        _convolve_forward,
    ),
    Case(
        "convolve_rgb_grad",
        "pipeline",
        "gradient of a loss of convolve_rgb w.r.t. the PSF",
        _convolve_gradient,
        forward="convolve_rgb",
    ),
)
