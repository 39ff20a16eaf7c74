"""``invglare psf``: compute a model's PSF and write it to EXR (and optionally a PNG preview)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from invglare.errors import NumericalError

log = logging.getLogger("invglare")

#: Radius (deg) of the black spot of the ISO 9358 veiling glare index reported for veiling models.
VGI_SPOT_RADIUS_DEG = 0.5

NORMALISATION = "fraction of the transmitted power per pixel (Y sums to 1 over the full plane)"


def run_psf(
    config_path: Path,
    out: Path,
    npix: int | None,
    pixel_scale_deg: float | None,
    wavelengths: str | None,
    half: bool,
    png: Path | None,
) -> None:
    import jax

    from invglare.config.model import build_model, model_to_config
    from invglare.files.exr import write_exr
    from invglare.files.toml import load_toml
    from invglare.models.veiling import VeilingGlare
    from invglare.optics.spectral import parse_wavelengths

    config = load_toml(config_path)
    lams = None if wavelengths is None else parse_wavelengths(wavelengths)
    model = build_model(
        config,
        base_dir=Path(config_path).parent,
        npix=npix,
        pixel_scale_deg=pixel_scale_deg,
        wavelengths_nm=lams,
        source=str(config_path),
    )
    psf = np.asarray(jax.jit(lambda m: m())(model))
    if not np.all(np.isfinite(psf)):
        raise NumericalError(f"the PSF of {config_path} has non-finite values")
    if isinstance(model, VeilingGlare):
        _write_veiling(model, psf, out, half, png)
        return
    prop = model.propagator
    scale = float(prop.output.pixel_scale_deg)
    energy = float(psf.sum() if psf.ndim == 2 else _luminance(psf).sum())
    write_exr(
        out,
        psf,
        pixel_scale_deg=scale,
        wavelengths_nm=[float(w) for w in model.spectrum.wavelengths_nm],
        config=model_to_config(model),
        attrs={"psfNormalisation": NORMALISATION, "propagationMethod": prop.method},
        half=half,
    )
    channels = "Y" if psf.ndim == 2 else "R,G,B"
    log.info(
        "wrote %s: %dx%d %s, %.4g deg/px, %s via %s, energy in field %.4f",
        out,
        psf.shape[0],
        psf.shape[1],
        channels,
        scale,
        prop.propagation,
        prop.method.upper(),
        energy,
    )
    if png is not None:
        from invglare.files.images import write_png

        write_png(png, log_preview(psf))
        log.info("wrote %s (log-scaled preview, 6 decades)", png)


def _write_veiling(model, psf: np.ndarray, out: Path, half: bool, png: Path | None) -> None:
    """A veiling-glare image has no propagator: its header carries the glare index instead."""
    from invglare.config.model import model_to_config
    from invglare.files.exr import write_exr

    vgi = float(model.veiling_glare_index(spot_radius_deg=VGI_SPOT_RADIUS_DEG))
    write_exr(
        out,
        psf,
        pixel_scale_deg=float(model.pixel_scale_deg),
        config=model_to_config(model),
        attrs={
            "psfNormalisation": "fraction of the light's flux per pixel (veiling glare only)",
            "veilingGlareIndex": vgi,
            "vgiSpotRadiusDeg": VGI_SPOT_RADIUS_DEG,
        },
        half=half,
    )
    log.info(
        "wrote %s: %dx%d Y, %.4g deg/px, %d ghosts, veiling glare index %.3g %% "
        "(ISO 9358, spot radius %.2g deg)",
        out,
        psf.shape[0],
        psf.shape[1],
        float(model.pixel_scale_deg),
        model.ghosts.n_ghosts,
        100 * vgi,
        VGI_SPOT_RADIUS_DEG,
    )
    if png is not None:
        from invglare.files.images import write_png

        write_png(png, log_preview(psf))
        log.info("wrote %s (log-scaled preview, 6 decades)", png)


def _luminance(rgb: np.ndarray) -> np.ndarray:
    # Rec. 709 / sRGB luminance weights, matching the default colourspace.
    return rgb @ np.array([0.2126, 0.7152, 0.0722])


def log_preview(psf: np.ndarray, decades: float = 6.0) -> np.ndarray:
    """Map a PSF to [0, 1] on a log scale covering `decades` below its peak."""
    peak = float(psf.max())
    if peak <= 0:
        return np.zeros_like(psf)
    return np.clip(1.0 + np.log10(np.maximum(psf / peak, 1e-30)) / decades, 0.0, 1.0)
