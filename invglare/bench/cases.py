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


CASES: tuple[Case, ...] = (
    Case("fft_floor_scipy", "floor", "scipy.fft.fft2, complex64, 2 workers", _scipy_fft),
    Case("fft_floor_pyfftw", "floor", "pyfftw fft2, complex64, 2 threads", _pyfftw_fft),
    Case("fft_jax", "pipeline", "bare jnp.fft.fft2, complex64 (JAX's own FFT)", _jax_fft),
    Case(
        "psf_mono",
        "pipeline",
        "disk raster (N/2) + FFT + |.|^2 + normalise, jitted",
        _psf_forward,
    ),
    Case(
        "psf_mono_grad",
        "pipeline",
        "d(sum w * PSF)/d(diameter) of psf_mono",
        _psf_gradient,
        forward="psf_mono",
    ),
)
