"""``invglare render`` and ``invglare scene``: glare on an HDR image, and the bundled scenes."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from invglare.errors import ConfigError, InputDataError

log = logging.getLogger("invglare")

MODES = ("convolve", "billboard")
OUTPUT_SUFFIXES = (".exr", ".png")


def run_scene(name: str, out: Path, npix: int, seed: int) -> None:
    from invglare.render.scenes import SCENES, write_scene

    if name not in SCENES:
        raise ConfigError(f"unknown scene {name!r}; bundled scenes: {', '.join(SCENES)}")
    write_scene(name, out, npix=npix, seed=seed)
    log.info("wrote %s (%s, %dx%d, linear cd/m^2)", out, name, npix, npix)


def psf_at_scale(model, scale_deg: float, max_npix: int):
    """The model's PSF resampled (energy-preserving) to `scale_deg` per pixel.

    The PSF is computed at the model's own sampling, which resolves the
    diffraction pattern, and then area-averaged onto the image's coarser pixels.
    """
    import jax

    from invglare.render.convolve import resample_psf

    psf = jax.jit(lambda m: m())(model)
    own_scale = float(model.propagator.output.pixel_scale_deg)
    if math.isclose(own_scale, scale_deg, rel_tol=1e-6):
        return psf
    field_deg = psf.shape[0] * own_scale
    npix = min(max_npix, max(3, math.ceil(field_deg / scale_deg)))
    npix += 1 - npix % 2  # odd: the centre pixel stays centred
    return resample_psf(psf, own_scale, scale_deg, npix)


def run_render(
    scene: Path,
    model_path: Path,
    out: Path,
    mode: str,
    threshold: float | None,
    max_bright: int,
    tonemap_name: str,
    exposure: float,
    pixel_scale_deg: float | None,
) -> None:
    import jax.numpy as jnp

    from invglare.io.config import load_toml
    from invglare.io.exr import read_exr, write_exr
    from invglare.io.images import write_png
    from invglare.io.model_config import build_model, model_to_config
    from invglare.render import (
        add_billboards,
        bright_pixel_list,
        convolve_psf,
        tonemap,
        validate_scene,
    )

    if mode not in MODES:
        raise ConfigError(f"--mode {mode!r} is not one of {', '.join(MODES)}")
    if out.suffix.lower() not in OUTPUT_SUFFIXES:
        raise ConfigError(f"--out must end in {' or '.join(OUTPUT_SUFFIXES)}, got {out.name!r}")
    img = read_exr(scene)
    image = validate_scene(img.data, name=str(scene))
    scale = pixel_scale_deg if pixel_scale_deg is not None else img.pixel_scale_deg
    if scale is None:
        raise InputDataError(
            f"{scene} has no pixelScaleDeg header; pass --pixel-scale-deg (degrees per pixel)"
        )
    config = load_toml(model_path)
    model = build_model(config, base_dir=model_path.parent, source=str(model_path))
    psf = psf_at_scale(model, scale, max_npix=2 * max(image.shape[:2]) + 1)
    if image.ndim == 3 and psf.ndim == 2:
        psf = jnp.repeat(psf[..., None], image.shape[2], axis=-1)
    if image.ndim == 2 and psf.ndim == 3:
        raise InputDataError(f"{scene} is monochrome (Y) but the model's PSF is RGB")
    image = jnp.asarray(image)
    if mode == "convolve":
        result = convolve_psf(image, psf)
    else:
        lum = image if image.ndim == 2 else image @ jnp.asarray([0.2126, 0.7152, 0.0722])
        level = float(jnp.max(lum)) / 100.0 if threshold is None else threshold
        bright = bright_pixel_list(image, level, max_bright)
        if int(bright.n_above) > max_bright:
            log.warning(
                "%d pixels exceed the threshold %.4g; only the %d brightest get billboards "
                "(raise --max-bright or --threshold)",
                int(bright.n_above),
                level,
                max_bright,
            )
        # Listed bright pixels are replaced by their spread light, so energy is conserved;
        # bright pixels beyond max_bright stay as they are.
        listed = (
            jnp.zeros(image.shape[:2])
            .at[bright.rows, bright.cols]
            .max(bright.valid.astype(image.dtype))
        )
        keep = 1.0 - (listed if image.ndim == 2 else listed[..., None])
        result = add_billboards(image * keep, bright, psf)
    result = np.asarray(result)
    if out.suffix.lower() == ".exr":
        write_exr(
            out,
            result,
            pixel_scale_deg=scale,
            config=model_to_config(model),
            attrs={"renderMode": mode, "scene": str(scene)},
        )
    else:
        params = {"exposure": exposure} if tonemap_name in ("gamma", "srgb") else {}
        write_png(out, np.asarray(tonemap(result, tonemap_name, **params)))
    log.info("wrote %s (%s, PSF %dpx at %.4g deg/px)", out, mode, psf.shape[0], scale)
