"""Model configurations: TOML tables to forward models.

Schema of a model config (every key but ``model.kind``, ``focal_length_mm`` and the
shapes has a default)::

    [model]
    kind = "aperture"             # the only model kind so far
    focal_length_mm = 17.0        # pupil-to-retina / lens-to-sensor distance
    propagation = "fraunhofer"    # or "fresnel" (the E term of Ritschel et al., eq. 3)
    aperture_npix = 256           # raster size of the aperture window
    window_mm = 4.1               # default: the aperture's extent plus 2 px each side
    method = "auto"               # "fft", "mft" or "auto"

    [[model.shapes]]              # union of "open" shapes times all "block" shapes
    kind = "disk"                 # disk, ellipse, polygon, capsule, image
    diameter_mm = 4.0

    [output]
    npix = 512
    pixel_scale_deg = 0.0004      # default: the FFT's native scale (fast path)

    [spectrum]
    wavelengths_nm = 550          # a number, a list, or "380:770:32"
    spectral = "exact"            # or "scaled" (copies of the reference PSF)
    reference_wavelength_nm = 575.0
    illuminant = "E"              # colour-science illuminant name, or "E"
    colourspace = "sRGB"          # linear RGB space of a spectral PSF
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from invglare.aperture import Aperture, shape_from_config, shape_to_config
from invglare.errors import ConfigError
from invglare.io.config import Section, check_sections
from invglare.models.aperture_psf import AperturePSF
from invglare.optics.propagator import METHODS, PROPAGATIONS
from invglare.optics.spectral import SPECTRAL_METHODS, parse_wavelengths

MODEL_KINDS = ("aperture",)
SECTIONS = ("model", "output", "spectrum")


def build_model(
    config: dict[str, Any],
    base_dir: str | Path | None = None,
    *,
    npix: int | None = None,
    pixel_scale_deg: float | None = None,
    wavelengths_nm: Any = None,
    source: str = "config",
) -> AperturePSF:
    """Build the forward model a config describes; keyword arguments override the config."""
    check_sections(config, SECTIONS, source)
    if "model" not in config:
        raise ConfigError(f"{source}: no [model] section")
    model = Section(config["model"], "model")
    kind = model.get("kind", str, required=True)
    if kind not in MODEL_KINDS:
        raise ConfigError(
            f"model.kind = {kind!r} is unknown; valid kinds: {', '.join(MODEL_KINDS)}"
        )
    focal = model.get("focal_length_mm", float, required=True)
    propagation = model.choice("propagation", PROPAGATIONS, "fraunhofer")
    aperture_npix = model.get("aperture_npix", int, 256)
    window = model.get("window_mm", float, None)
    method = model.choice("method", METHODS, "auto")
    tables = model.get("shapes", list, required=True)
    model.finish()
    if not tables:
        raise ConfigError("model.shapes is empty; give at least one [[model.shapes]] table")
    shapes = tuple(
        shape_from_config(t, f"model.shapes[{i}]", base_dir=base_dir) for i, t in enumerate(tables)
    )

    output = Section(config.get("output", {}), "output")
    out_npix = output.get("npix", int, 512)
    scale = output.get("pixel_scale_deg", float, None)
    output.finish()

    spectrum = Section(config.get("spectrum", {}), "spectrum")
    lams = spectrum.get("wavelengths_nm", (float, list, str), 550.0)
    spectral = spectrum.choice("spectral", SPECTRAL_METHODS, "exact")
    reference = spectrum.get("reference_wavelength_nm", float, 575.0)
    illuminant = spectrum.get("illuminant", str, "E")
    colourspace = spectrum.get("colourspace", str, "sRGB")
    spectrum.finish()

    return AperturePSF.build(
        Aperture(shapes),
        focal_length_mm=focal,
        wavelengths_nm=parse_wavelengths(lams if wavelengths_nm is None else wavelengths_nm),
        npix=out_npix if npix is None else npix,
        pixel_scale_deg=scale if pixel_scale_deg is None else pixel_scale_deg,
        aperture_npix=aperture_npix,
        window_mm=window,
        propagation=propagation,
        method=method,
        spectral=spectral,
        reference_wavelength_nm=reference,
        illuminant=illuminant,
        colourspace=colourspace,
    )


def model_to_config(model: AperturePSF) -> dict[str, Any]:
    """The config of a built model with every choice made explicit (for file headers)."""
    prop, spec = model.propagator, model.spectrum
    return {
        "model": {
            "kind": "aperture",
            "focal_length_mm": float(prop.focal_length_mm),
            "propagation": prop.propagation,
            "aperture_npix": prop.grid.npix,
            "window_mm": float(prop.grid.width_mm),
            "method": prop.method,
            "shapes": [shape_to_config(s) for s in model.aperture.shapes],
        },
        "output": {
            "npix": prop.output.npix,
            "pixel_scale_deg": float(prop.output.pixel_scale_deg),
        },
        "spectrum": {
            "wavelengths_nm": [float(w) for w in spec.wavelengths_nm],
            "spectral": spec.spectral,
            "reference_wavelength_nm": spec.reference_wavelength_nm,
            "illuminant": spec.illuminant,
            "colourspace": spec.colourspace,
        },
    }
