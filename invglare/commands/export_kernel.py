"""``invglare export-kernel``: a model's PSF as a Blender or Unreal convolution kernel (EXR).

The layout and what each renderer does with the file are in `invglare.render.kernels`;
this command builds the model, checks it can be one kernel (shift invariant), resamples
its PSF to the frame's pixel scale as `invglare render` does, writes a linear float32 RGB
EXR and tells the user how to set the renderer up.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from invglare.errors import ConfigError, NumericalError, PhysicsRangeError

log = logging.getLogger("invglare")

#: The largest kernel written without an explicit --npix (a 4097² RGB float32 EXR is 200 MB).
MAX_DEFAULT_NPIX = 4097


def parse_viewport(text: str | None) -> tuple[int, int] | None:
    """``"1920x1080"`` as ``(1920, 1080)``; None passes; anything else is a ConfigError."""
    if text is None:
        return None
    parts = str(text).lower().replace("×", "x").split("x")
    try:
        width, height = (int(p) for p in parts)
    except ValueError:
        raise ConfigError(
            f"--viewport must be WIDTHxHEIGHT in pixels (e.g. 1920x1080), got {text!r}"
        ) from None
    if min(width, height) < 1:
        raise ConfigError(f"--viewport must be at least 1x1 px, got {text!r}")
    return width, height


def _frame_scale_deg(
    model, pixel_scale_deg: float | None, fov_deg: float | None, viewport: tuple[int, int] | None
) -> float:
    from invglare.render.kernels import viewport_pixel_scale_deg

    if fov_deg is not None:
        return viewport_pixel_scale_deg(fov_deg, viewport[0])
    if pixel_scale_deg is not None:
        if not (math.isfinite(pixel_scale_deg) and pixel_scale_deg > 0):
            raise PhysicsRangeError(
                f"--pixel-scale-deg must be a finite number > 0 deg/px, got {pixel_scale_deg!r}"
            )
        return float(pixel_scale_deg)
    return float(model.pixel_scale_deg)


def _check_options(
    out: Path,
    pixel_scale_deg: float | None,
    fov_deg: float | None,
    viewport: tuple[int, int] | None,
) -> None:
    from invglare.commands import options
    from invglare.files.outputs import output_file

    output_file(out, "--out", (".exr",))
    options.positive(pixel_scale_deg, "--pixel-scale-deg")
    if fov_deg is not None and not (math.isfinite(fov_deg) and 0 < fov_deg < 180):
        raise PhysicsRangeError(f"--fov-deg must lie in (0, 180) degrees, got {fov_deg!r}")
    if fov_deg is not None and viewport is None:
        raise ConfigError("--fov-deg needs --viewport (the width it spans)")
    if fov_deg is not None and pixel_scale_deg is not None:
        raise ConfigError(
            "give the frame's pixel scale once: --pixel-scale-deg, or --fov-deg with --viewport"
        )


def run_export_kernel(
    config_path: Path,
    out: Path,
    target: str,
    npix: int | None = None,
    pixel_scale_deg: float | None = None,
    wavelengths: str | None = None,
    viewport: str | None = None,
    fov_deg: float | None = None,
) -> dict:
    """Write `config_path`'s PSF as `target`'s kernel to `out`; return the header values.

    **Raises** (all before the PSF is computed): `ConfigError` for an unknown target, an
    even or too small `npix`, an output that is not ``.exr``, a malformed viewport,
    ``--fov-deg`` without ``--viewport``, or a model that is not shift invariant (one
    kernel cannot render a PSF that changes with the light's direction);
    `PhysicsRangeError` for a bad pixel scale or field of view. After it:
    `NumericalError` for a non-finite PSF, `PhysicsRangeError` when an Unreal kernel's
    brightest pixel is not its centre.
    """
    from invglare.commands import options
    from invglare.config.section import precheck_model_config

    config = precheck_model_config(config_path)  # a typo is reported before JAX loads
    from invglare.render.kernels import check_kernel_request

    with options.named("--for"):
        name = check_kernel_request(target)
    with options.named("--npix"):
        check_kernel_request(name, npix)
    view = parse_viewport(viewport)
    out = Path(out)
    _check_options(out, pixel_scale_deg, fov_deg, view)

    from invglare.commands.render import psf_at_scale
    from invglare.config.model import build_model
    from invglare.files.exr import write_exr
    from invglare.render import kernels

    lams = options.wavelengths(wavelengths)
    if npix is not None:  # the kernel is RGB, resampled from a PSF at least as large
        options.raster(npix, "--npix", channels=3, copies=4)
    model = build_model(
        config, base_dir=Path(config_path).parent, wavelengths_nm=lams, source=str(config_path)
    )
    if not model.shift_invariant:
        raise ConfigError(
            f"{config_path}: the model's image depends on the light's direction "
            f"({type(model).__name__}, e.g. masking = 'position' or lens ghosts), so no single "
            "convolution kernel renders it; render it with `invglare render --mode billboard`"
        )
    scale = _frame_scale_deg(model, pixel_scale_deg, fov_deg, view)
    if npix is not None:
        cap = npix
    elif view is not None:
        cap = min(view) - 1 + min(view) % 2  # the largest odd size on the screen's minor axis
    else:
        cap = MAX_DEFAULT_NPIX
    log.info("computing the PSF of %s and resampling it to %.4g deg/px", config_path, scale)
    psf = np.asarray(psf_at_scale(model, scale, max_npix=cap))
    if not np.all(np.isfinite(psf)):
        raise NumericalError(f"the PSF of {config_path} has non-finite values")
    kernel = np.asarray(kernels.kernel_for(name, psf, npix), np.float32)
    n = kernel.shape[0]
    if name == "unreal":
        dy, dx = kernels.peak_offset_px(kernel)
        if (dy, dx) != (0, 0):
            c = n // 2
            raise PhysicsRangeError(
                f"the brightest pixel of {config_path}'s PSF is {dy} rows, {dx} columns from its "
                f"centre ({float(kernel[c + dy, c + dx].max()):.4g} against "
                f"{float(kernel[c, c].max()):.4g} at the centre); Unreal's bloom expects it at "
                "the centre (e.g. a defocused or Fresnel PSF): use --for blender instead"
            )
    energy = [float(v) for v in kernels.channel_energy(kernel)]
    centre = [float(v) for v in kernels.centre_fraction(kernel)]
    header = {
        "kernelTarget": name,
        "kernelChannelEnergy": energy,
        "kernelCentreFraction": centre,
        "kernelPointReflected": int(name == "blender"),
    }
    if view is not None:
        header["unrealConvolutionScale"] = kernels.unreal_convolution_scale(n, view)
    write_exr(
        out,
        kernel,
        pixel_scale_deg=scale,
        wavelengths_nm=None if model.wavelengths_nm is None else list(model.wavelengths_nm),
        config=model.to_config(),
        attrs=header,
    )
    lines = describe(name, out, n, scale, energy, centre, view)
    for line in lines:
        log.info("%s", line)
    return header


def describe(
    target: str,
    out: Path,
    npix: int,
    scale_deg: float,
    energy: list[float],
    centre: list[float],
    viewport: tuple[int, int] | None,
) -> list[str]:
    """The lines the command prints: what was written and how to set the renderer up."""
    rgb = ", ".join(f"{v:.4g}" for v in energy)
    lines = [
        f"wrote {out}: {npix}x{npix} RGB float32 (linear) at {scale_deg:.4g} deg/px, centre "
        f"pixel ({npix // 2}, {npix // 2}); channel energies R, G, B = {rgb} (the rest of the "
        "light falls outside the kernel)"
    ]
    tinted = max(energy) > 0 and (max(energy) - min(energy)) > 1e-3 * max(energy)
    if target == "blender":
        lines += [
            "Blender: load it as an Image (colour space Linear) and feed a Convolve node "
            "(Kernel Data Type: Color) or a Glare node (Type: Kernel, Quality: High, "
            f"Threshold 0); the frame must be at {scale_deg:.4g} deg/px. The kernel is "
            "stored rotated by 180 deg, because Blender gathers with its kernel.",
            "Blender normalises each channel of a kernel to sum 1 (the Glare node always, the "
            "Convolve node unless Normalize Kernel is off): "
            + (
                f"this kernel's tint (R:G:B energies {rgb}) becomes neutral, a white light "
                "gets a white glare. "
                if tinted
                else "this kernel's channels hold the same energy to within 0.1 %, so only "
                "its level changes (to that of a PSF holding all of the light). "
            )
            + "To keep the model's colour and level: Convolve with Normalize Kernel off "
            f"(exactly `invglare render`), or set the Glare node's Tint to ({rgb}) (linear "
            "values, typed in; they may exceed 1) with Strength 1 and take its Glare output "
            "(its Image output adds the unspread image as well).",
        ]
    else:
        frac = ", ".join(f"{v:.4g}" for v in centre)
        scale_text = (
            f"Convolution Scale = {npix}/{min(viewport)} = "
            f"{npix / min(viewport):.6g} for a {viewport[0]}x{viewport[1]} viewport"
            if viewport is not None
            else f"Convolution Scale = {npix} / (the viewport's minor axis in px)"
        )
        lines += [
            "Unreal: import it as a texture (HDR, no mipmaps, no sRGB), set Bloom > Method "
            f"Convolution, Convolution Kernel to it, {scale_text} (one texel per screen "
            f"pixel at {scale_deg:.4g} deg/px), Convolution Center (0.5, 0.5): the centre "
            "pixel's centre is UV (0.5, 0.5) exactly.",
            f"The peak is the centre pixel, unclipped: it holds R, G, B = {frac} of each "
            "channel's energy (the light that stays focused; the rest scatters), the model's "
            "own core-to-halo ratio. Keep Scatter Dispersion at 1 to use it as is"
            + (
                f"; the channels' energies differ ({rgb}, header kernelChannelEnergy): "
                "normalised channel by channel they would lose that tint."
                if tinted
                else "."
            ),
        ]
    return lines
