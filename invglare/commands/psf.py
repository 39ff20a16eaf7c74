"""``invglare psf``: compute a model's PSF and write it to EXR (and optionally a PNG preview)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from invglare.errors import NumericalError

log = logging.getLogger("invglare")


def run_psf(
    config_path: Path,
    out: Path,
    npix: int | None,
    pixel_scale_deg: float | None,
    wavelengths: str | None,
    half: bool,
    png: Path | None,
) -> None:
    from invglare.config.section import precheck_model_config

    config = precheck_model_config(config_path)  # a typo is reported before JAX loads
    import jax

    from invglare._core.colour import rec709_luminance_np
    from invglare._core.memory import check_compiled_memory, check_memory
    from invglare.commands import options
    from invglare.config.model import build_model
    from invglare.files.exr import write_exr
    from invglare.files.outputs import output_file

    out = output_file(out, "--out", (".exr",))
    png = None if png is None else output_file(png, "--png", (".png",))
    options.count(npix, "--npix")
    options.positive(pixel_scale_deg, "--pixel-scale-deg")
    lams = options.wavelengths(wavelengths)
    n_lams = 1 if lams is None else len(lams)
    if npix is not None:
        options.raster(npix, "--npix", channels=n_lams, copies=2)
    if lams is not None:  # at least a 64^2 PSF per wavelength, whatever the config says
        side = npix or 64
        check_memory(
            2 * 4.0 * side**2 * n_lams,
            f"{n_lams} wavelengths (--wavelengths-nm) of a {side}x{side} PSF each",
        )
    with options.given(
        ("--npix", npix, "npix"),
        ("--pixel-scale-deg", pixel_scale_deg, "pixel_scale_deg"),
        ("--wavelengths-nm", wavelengths, "wavelength"),
    ):
        model = build_model(
            config,
            base_dir=Path(config_path).parent,
            npix=npix,
            pixel_scale_deg=pixel_scale_deg,
            wavelengths_nm=lams,
            source=str(config_path),
        )
    compiled = jax.jit(lambda m: m()).lower(model).compile()
    check_compiled_memory(compiled, f"the PSF of {config_path}")
    psf = np.asarray(compiled(model))
    if not np.all(np.isfinite(psf)):
        raise NumericalError(f"the PSF of {config_path} has non-finite values")
    scale = float(model.pixel_scale_deg)
    header = model.header()
    wavelengths_nm = model.wavelengths_nm
    write_exr(
        out,
        psf,
        pixel_scale_deg=scale,
        wavelengths_nm=None if wavelengths_nm is None else list(wavelengths_nm),
        config=model.to_config(),
        attrs=header,
        half=half,
    )
    energy = float(psf.sum() if psf.ndim == 2 else rec709_luminance_np(psf).sum())
    details = ", ".join(f"{k} {_shown(v)}" for k, v in header.items() if k != "psfNormalisation")
    log.info(
        "wrote %s: %dx%d %s, %.4g deg/px, energy in field %.4f (%s)",
        out,
        psf.shape[0],
        psf.shape[1],
        "Y" if psf.ndim == 2 else "R,G,B",
        scale,
        energy,
        details,
    )
    if png is not None:
        from invglare.files.images import write_png

        write_png(png, log_preview(psf))
        log.info("wrote %s (log-scaled preview, 6 decades)", png)


def _shown(value) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def log_preview(psf: np.ndarray, decades: float = 6.0) -> np.ndarray:
    """Map a PSF to [0, 1] on a log scale covering `decades` below its peak."""
    peak = float(psf.max())
    if peak <= 0:
        return np.zeros_like(psf)
    return np.clip(1.0 + np.log10(np.maximum(psf / peak, 1e-30)) / decades, 0.0, 1.0)
