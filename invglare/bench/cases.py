"""Benchmark cases: each builds, for a size N, a zero-argument callable to time.

*Floor* cases time a bare 2D FFT of an N x N complex64 array, the least work any
N x N diffraction pipeline must do; *pipeline* cases are compared with the
fastest floor measured in the same run. Later models add their cases to
:data:`CASES`.

N is the output size; apertures are rasterised on N/2 x N/2 grids (the FFT pads
them to N, the Nyquist sampling of the PSF). Everything runs in float32, the
rendering precision. A gradient case differentiates a weighted sum of its forward
case's output (fixed random weights, so no entry of the output is special) and
records the ratio to that forward case (`vs_forward`).
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


def _weights(shape: tuple[int, ...], seed: int):
    """Fixed random weights for the scalar a gradient case differentiates."""
    import jax.numpy as jnp

    return jnp.asarray(np.random.default_rng(seed).random(shape), jnp.float32)


def _night_eye_on_grid(n: int):
    """The full night eye with its stamp windows fixed for an N/2 grid (so it jits)."""
    from invglare._core.grids import ApertureGrid
    from invglare.aperture.eye import night_eye

    eye = night_eye(0)
    # The pupil plus 2 %: the transmission is 0 outside the pupil, so a wider window
    # would only coarsen the raster.
    grid = ApertureGrid.from_width(n // 2, 1.02 * eye.extent_mm())
    return eye.with_stamp_windows(grid), grid


def _eye_raster(n: int):
    import equinox as eqx

    eye, grid = _night_eye_on_grid(n)
    raster = eqx.filter_jit(lambda e, g: e.transmission(g))
    return lambda: raster(eye, grid)


def _eye_raster_gradient(n: int):
    import equinox as eqx
    import jax.numpy as jnp

    eye, grid = _night_eye_on_grid(n)
    weights = _weights((n // 2, n // 2), 3)

    # Every float leaf of the eye (pupil, lids, lash / particle / grating counts and
    # sizes); the random keys are not floats and are left alone by filter_grad.
    @eqx.filter_jit
    @eqx.filter_grad
    def grad(e, g):
        return jnp.sum(e.transmission(g) * weights)

    return lambda: grad(eye, grid)


def _kakimoto_eye(n: int, **options):
    """Kakimoto glare of the daylight eye, monochrome at 550 nm, N output, N/2 aperture.

    `options` go to `KakimotoGlare.build` (e.g. the masking).
    """
    from invglare.aperture.eye import lashed_daylight_eye
    from invglare.models.kakimoto import KakimotoGlare

    return KakimotoGlare.build(
        lashed_daylight_eye(0),
        focal_length_mm=17.0,
        obstacle_distance_mm=8.0,
        npix=n,
        aperture_npix=n // 2,
        colour="spectral",
        wavelengths_nm=550.0,
        **options,
    )


def _kakimoto_eye_forward(n: int):
    import equinox as eqx

    model = _kakimoto_eye(n)
    forward = eqx.filter_jit(lambda m: m())
    return lambda: forward(model)


#: Lights of the position-dependent render case, and its frame scale in model pixels.
_POSITION_LIGHTS = 16
_POSITION_FRAME_SCALE = 4


def _position_render(n: int):
    """An N x N frame with 16 lights on a ring, each rendered with the PSF of its direction."""
    import jax.numpy as jnp

    from invglare.render.bright import bright_pixel_list
    from invglare.render.position_glare import render_position_glare

    probe = _kakimoto_eye(n)
    scale = _POSITION_FRAME_SCALE * float(probe.pixel_scale_deg)
    angle = np.linspace(0.0, 2.0 * np.pi, _POSITION_LIGHTS, endpoint=False)
    rows = np.round(n // 2 + 0.25 * n * np.sin(angle)).astype(int)
    cols = np.round(n // 2 + 0.25 * n * np.cos(angle)).astype(int)
    frame = np.full((n, n), 0.01, np.float32)
    frame[rows, cols] = 1000.0
    model = _kakimoto_eye(n, masking="position", max_light_angle_deg=0.3 * n * scale)
    image = jnp.asarray(frame)
    bright = bright_pixel_list(image, 100.0, _POSITION_LIGHTS)
    max_npix = n // 4 + 1
    return lambda: render_position_glare(model, image, bright, scale, max_npix, progress=False)


def _kakimoto_eye_gradient(n: int):
    import equinox as eqx
    import jax.numpy as jnp

    model = _kakimoto_eye(n)
    weights = _weights((n, n), 4)

    # With respect to every float leaf of the eye aperture (what a fit frees), not the
    # propagator's sampling or the spectrum.
    @eqx.filter_jit
    @eqx.filter_grad
    def grad(aperture, m):
        return jnp.sum(eqx.tree_at(lambda mm: mm.aperture, m, aperture)() * weights)

    return lambda: grad(model.aperture, model)


def _kakimoto_camera_rgb(n: int):
    import equinox as eqx

    from invglare.aperture.camera import CameraAperture, CrossScreen, Diaphragm
    from invglare.models.kakimoto import KakimotoGlare

    diaphragm = Diaphragm(6, f_number=8.0, focal_length_mm=50.0)
    # 0.2 mm lines, or at tiny sizes the finest spacing the N/2 raster resolves (the model
    # refuses a filter its raster aliases; the cost does not depend on the spacing).
    pitch = 2.0 * diaphragm.extent_radius_mm() / (n // 2 - 4)
    camera = CameraAperture(
        diaphragm,
        filter=CrossScreen((0.0, 90.0), spacing_mm=max(0.2, 2.5 * pitch), duty_cycle=0.1),
    )
    model = KakimotoGlare.build(
        camera, focal_length_mm=50.0, obstacle_distance_mm=20.0, npix=n, aperture_npix=n // 2
    )
    forward = eqx.filter_jit(lambda m: m())
    return lambda: forward(model)


def _veiling_cooke(n: int):
    """The Cooke triplet's paraxial ghosts (examples/veiling_cooke.toml) on an N x N screen."""
    from pathlib import Path

    import equinox as eqx
    import jax.numpy as jnp

    from invglare.config.model import build_model
    from invglare.files.toml import load_toml

    example = Path(__file__).resolve().parents[2] / "examples" / "veiling_cooke.toml"
    if not example.is_file():  # an installed wheel carries no examples/
        return None
    model = build_model(load_toml(example), base_dir=example.parent, npix=n)
    angle = jnp.asarray([3.0, 1.5])
    forward = eqx.filter_jit(lambda m, a: m(a))
    return lambda: forward(model, angle)


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
    Case(
        "eye_raster",
        "pipeline",
        "night_eye transmission P*t_o (pupil, lids, 80 lashes, 1000 particles, 200 gratings) "
        "on an N/2 grid, stamp windows fixed, jitted",
        _eye_raster,
    ),
    Case(
        "eye_raster_grad",
        "pipeline",
        "d(sum w * transmission)/d(every float leaf of the night eye)",
        _eye_raster_gradient,
        forward="eye_raster",
    ),
    Case(
        "kakimoto_eye_psf",
        "pipeline",
        "KakimotoGlare of lashed_daylight_eye (fixed mask), 550 nm mono: N/2 raster + FFT to N",
        _kakimoto_eye_forward,
    ),
    Case(
        "kakimoto_eye_psf_grad",
        "pipeline",
        "d(sum w * PSF)/d(every float leaf of the daylight eye) of kakimoto_eye_psf",
        _kakimoto_eye_gradient,
        forward="kakimoto_eye_psf",
    ),
    Case(
        "kakimoto_position_render",
        "pipeline",
        "masking='position' render of an N x N frame: 16 lights on a ring, each its own "
        "daylight-eye PSF (N/2 raster + FFT to N, 8 per compiled call), resampled to 4x the "
        "model's pixel scale and stamped as an (N/4+1)^2 billboard",
        _position_render,
    ),
    Case(
        "kakimoto_camera_rgb",
        "pipeline",
        "KakimotoGlare of a 6-blade f/8 50 mm camera + 2-way cross screen, paper_rgb "
        "(680/530/460 nm): N/2 raster + 3 FFTs to N",
        _kakimoto_camera_rgb,
    ),
    Case(
        "veiling_cooke",
        "pipeline",
        "VeilingGlare of the Cooke triplet's paraxial ghosts for a light at (3, 1.5) deg: "
        "coefficients aggregated in Fourier space + separable evaluation to N",
        _veiling_cooke,
    ),
)
