"""Model configurations: TOML tables to forward models.

Schema of a model config (every key but ``model.kind``, ``focal_length_mm`` and the
shapes has a default)::

    [model]
    kind = "aperture"             # "aperture", "eye" or "camera" (see below)
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

The kinds ``"eye"`` and ``"camera"`` are the wave-optics glare model of Kakimoto et al.
(:class:`~invglare.models.kakimoto.KakimotoGlare`): an obstacle image (lids and lashes,
or a cross-screen filter) masked by a pupil (the eye's, or a diaphragm). They take no
``model.shapes``; instead::

    [model]
    kind = "eye"
    focal_length_mm = 17.0        # for a camera: default the diaphragm's focal length
    obstacle_distance_mm = 8.0    # obstacle plane to pupil (default 8 eye, 0 camera)
    masking = "fixed"             # or "position" (the obstacle scrolls with the light)
    colour = "spectral"           # or "paper_rgb" (680/530/460 nm as R, G, B)
    max_light_angle_deg = 0.0

    [model.eye]                   # see invglare.config.eye.eye_from_config
    seed = 7
    [model.eye.pupil]
    diameter_mm = 3.0

    [model.camera]                # for kind = "camera": invglare.config.camera.camera_from_config
    [model.camera.diaphragm]
    n_blades = 6
    f_number = 8.0
    focal_length_mm = 50.0

The kind ``"veiling"`` (lens ghosts as Fourier series, :mod:`invglare.config.veiling`)
has its own schema; see ``examples/veiling_cooke.toml``. The kind ``"temporal"`` (the dynamic
eye of Ritschel et al., :func:`invglare.models.temporal.temporal_from_config`) likewise; see
``examples/temporal_eye.toml``.

Without ``[spectrum] wavelengths_nm`` a spectral model uses 380:770:32 and a paper_rgb
model 680/530/460 nm; one wavelength gives a monochrome PSF (what a fit needs).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from invglare.aperture import Aperture, shape_to_config
from invglare.aperture.camera import CameraAperture, camera_to_config
from invglare.aperture.eye import EyeAperture, eye_to_config
from invglare.config.camera import camera_from_config
from invglare.config.eye import eye_from_config
from invglare.config.section import Section, check_sections
from invglare.config.shapes import shape_from_config
from invglare.config.veiling import veiling_from_config, veiling_to_config
from invglare.errors import ConfigError
from invglare.models.aperture_psf import AperturePSF
from invglare.models.kakimoto import COLOURS, MASKINGS, KakimotoGlare, kakimoto_to_config
from invglare.models.temporal import TemporalGlare, temporal_from_config, temporal_to_config
from invglare.models.veiling import VeilingGlare
from invglare.optics.propagator import METHODS, PROPAGATIONS
from invglare.optics.spectral import SPECTRAL_METHODS, parse_wavelengths

MODEL_KINDS = ("aperture", "eye", "camera", "veiling", "temporal")
GlareModel = AperturePSF | KakimotoGlare | VeilingGlare | TemporalGlare
SECTIONS = ("model", "output", "spectrum")
_GLARE_KEYS = ("obstacle_distance_mm", "masking", "colour", "max_light_angle_deg")


def build_model(
    config: dict[str, Any],
    base_dir: str | Path | None = None,
    *,
    npix: int | None = None,
    pixel_scale_deg: float | None = None,
    wavelengths_nm: Any = None,
    source: str = "config",
) -> GlareModel:
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
    if kind == "veiling":
        return veiling_from_config(
            config,
            base_dir,
            npix=npix,
            pixel_scale_deg=pixel_scale_deg,
            wavelengths_nm=wavelengths_nm,
            source=source,
        )
    if kind == "temporal":
        return temporal_from_config(
            config,
            base_dir,
            npix=npix,
            pixel_scale_deg=pixel_scale_deg,
            wavelengths_nm=wavelengths_nm,
        )
    if kind == "aperture":
        focal = model.get("focal_length_mm", float, required=True)
        tables = model.get("shapes", list, required=True)
        if not tables:
            raise ConfigError("model.shapes is empty; give at least one [[model.shapes]] table")
        aperture = Aperture(
            tuple(
                shape_from_config(t, f"model.shapes[{i}]", base_dir=base_dir)
                for i, t in enumerate(tables)
            )
        )
    else:
        table = model.get(kind, dict, required=True)
        if kind == "eye":
            aperture = eye_from_config(table, "model.eye")
            focal = model.get("focal_length_mm", float, 17.0)
            distance = model.get("obstacle_distance_mm", float, 8.0)
        else:
            aperture = camera_from_config(table, "model.camera")
            focal = model.get("focal_length_mm", float, None)
            if focal is None:
                focal = float(aperture.diaphragm.focal_length_mm)
            distance = model.get("obstacle_distance_mm", float, 0.0)
        glare = dict(
            obstacle_distance_mm=distance,
            masking=model.choice("masking", MASKINGS, "fixed"),
            colour=model.choice("colour", COLOURS, "spectral"),
            max_light_angle_deg=model.get("max_light_angle_deg", float, 0.0),
        )
    sampling = dict(
        propagation=model.choice("propagation", PROPAGATIONS, "fraunhofer"),
        aperture_npix=model.get("aperture_npix", int, 256),
        window_mm=model.get("window_mm", float, None),
        method=model.choice("method", METHODS, "auto"),
    )
    model.finish()

    output = Section(config.get("output", {}), "output")
    out_npix = output.get("npix", int, 512)
    sampling["npix"] = out_npix if npix is None else npix
    scale = output.get("pixel_scale_deg", float, None)
    sampling["pixel_scale_deg"] = scale if pixel_scale_deg is None else pixel_scale_deg
    output.finish()

    spectrum = Section(config.get("spectrum", {}), "spectrum")
    lams = spectrum.get("wavelengths_nm", (float, list, str), 550.0 if kind == "aperture" else None)
    colour = dict(
        spectral=spectrum.choice("spectral", SPECTRAL_METHODS, "exact"),
        reference_wavelength_nm=spectrum.get("reference_wavelength_nm", float, 575.0),
        illuminant=spectrum.get("illuminant", str, "E"),
        colourspace=spectrum.get("colourspace", str, "sRGB"),
    )
    spectrum.finish()
    if wavelengths_nm is not None:
        lams = wavelengths_nm
    lams = None if lams is None else parse_wavelengths(lams)

    if kind == "aperture":
        return AperturePSF.build(
            aperture, focal_length_mm=focal, wavelengths_nm=lams, **sampling, **colour
        )
    return KakimotoGlare.build(
        aperture, focal_length_mm=focal, wavelengths_nm=lams, **glare, **sampling, **colour
    )


def model_to_config(model: GlareModel) -> dict[str, Any]:
    """The config of a built model with every choice made explicit (for file headers).

    ``build_model(model_to_config(model))`` rebuilds the same model.
    """
    if isinstance(model, VeilingGlare):
        return veiling_to_config(model)
    if isinstance(model, TemporalGlare):
        return temporal_to_config(model)
    prop, spec = model.propagator, model.spectrum
    table: dict[str, Any] = {
        "focal_length_mm": float(prop.focal_length_mm),
        "propagation": prop.propagation,
        "aperture_npix": prop.grid.npix,
        "window_mm": float(prop.grid.width_mm),
        "method": prop.method,
    }
    if isinstance(model, KakimotoGlare):
        choices = kakimoto_to_config(model)
        table |= {k: choices[k] for k in _GLARE_KEYS}
        if isinstance(model.aperture, EyeAperture):
            table = {"kind": "eye", **table, "eye": eye_to_config(model.aperture)}
        elif isinstance(model.aperture, CameraAperture):
            table = {"kind": "camera", **table, "camera": camera_to_config(model.aperture)}
        else:
            raise ConfigError(
                f"no config form for a Kakimoto model of a {type(model.aperture).__name__}"
            )
    else:
        table = {
            "kind": "aperture",
            **table,
            "shapes": [shape_to_config(s) for s in model.aperture.shapes],
        }
    return {
        "model": table,
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


def model_pixel_scale_deg(model: GlareModel) -> float:
    """Degrees of field per pixel of a built model's image."""
    if isinstance(model, VeilingGlare | TemporalGlare):
        return float(model.pixel_scale_deg)
    return float(model.propagator.output.pixel_scale_deg)


def model_wavelengths_nm(model: GlareModel) -> list[float] | None:
    """The wavelengths (nm) a built model's image is made at; None for the veiling model,
    whose ghosts are drawn without a wavelength."""
    if isinstance(model, VeilingGlare):
        return None
    return [float(w) for w in np.asarray(model.spectrum.wavelengths_nm).reshape(-1)]
