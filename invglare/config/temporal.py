"""The temporal model's config (``model.kind = "temporal"``): the dynamic eye of Ritschel et al."""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import numpy as np

from invglare._core.memory import check_psf_memory
from invglare.config.eye import eye_from_config
from invglare.config.raster import KEEP_GRID, GridRequest, square_npix
from invglare.config.section import MODEL_SECTIONS, Section, check_sections
from invglare.dynamics import (
    Accommodation,
    EyeDynamics,
    LensMesh,
    LidMotion,
    PupilDynamics,
    VitreousBody,
)
from invglare.errors import ConfigError, PhysicsRangeError, prefixed
from invglare.models.temporal import (
    _DYNAMICS_PARTS,
    BRIGHTNESS,
    EYE_FOCAL_LENGTH_MM,
    FRESNEL_MODES,
    TemporalGlare,
)
from invglare.optics.spectral import COPY_WEIGHTINGS, DEFAULT_WAVELENGTHS, parse_wavelengths


def _part_classes() -> dict[str, type]:
    return {
        "pupil": PupilDynamics,
        "accommodation": Accommodation,
        "lens": LensMesh,
        "vitreous": VitreousBody,
        "lids": LidMotion,
    }


def _read_part(cls: type, table: Any, where: str):
    """Build a dynamics part from a table whose keys are the part's fields."""
    sec = Section(table, where)
    args: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        default = f.default if f.default is not dataclasses.MISSING else None
        if isinstance(default, bool):
            kind: Any = bool
        elif isinstance(default, int):
            kind = int
        elif isinstance(default, tuple):
            kind = list
        else:
            kind = float
        value = sec.get(f.name, kind, None)
        if value is None:
            continue
        if kind is list:
            if len(value) != len(default) or not all(
                isinstance(v, int | float) and not isinstance(v, bool) for v in value
            ):
                raise ConfigError(
                    f"{where}.{f.name} must be a list of {len(default)} numbers, got {value!r}"
                )
            value = tuple(float(v) for v in value)
        args[f.name] = value
    sec.finish()
    try:
        return cls(**args)
    except (ConfigError, PhysicsRangeError) as err:
        raise type(err)(f"{where}: {err}") from err


def temporal_from_config(
    config: dict[str, Any],
    base_dir: Any = None,
    grid: GridRequest = KEEP_GRID,
    source: str = "config",
) -> TemporalGlare:
    """Build a :class:`TemporalGlare` from a model config (``model.kind = "temporal"``).

    **Arguments:**

    - `config`: the whole parsed TOML (sections ``model``, ``output``, ``spectrum``).
    - `base_dir`: what the eye's relative image paths are resolved against.
    - `grid`: its `npix` and `wavelengths_nm` override ``output.npix`` and
      ``spectrum.wavelengths_nm``; a `pixel_scale_deg` is refused (the PSF is at the FFT's
      native scale).

    ```toml
    [model]
    kind = "temporal"
    aperture_npix = 256            # default output.npix / 2
    focal_length_mm = 17.0         # pupil-to-retina distance d of eq. 3 (default 17)
    fresnel = "retina"             # E at d, alias-free (the paper's eq. 3, the default);
                                   #   "effective": E at fresnel_distance_mm (an
                                   #   approximation: a defocus of 1000 / d D); "none": E = 1
    # fresnel_distance_mm = 600.0  # with fresnel = "effective" only
    window_mm = 8.5                # default: the largest pupil of the dynamics + 2 px
    fps = 30.0
    seed = 0                       # or key_data = [..] (what the model's to_config() writes)
    field_luminance_cd_m2 = 100.0  # adaptation when no frame is given
    luminance_scale = 1.0          # cd/m^2 per frame unit
    brightness = "transmitted"     # eq. 3's K: glare ~ pupil area (default), or "unit"
    tonemap = "gamma"              # any of invglare.render.TONEMAPS
    [model.tonemap_params]         # keyword parameters of the tone map
    exposure = 1.0
    gamma = 2.2
    [model.eye]                    # invglare.config.eye.eye_from_config
    [model.dynamics.pupil]         # fields of PupilDynamics (and of Accommodation,
    hippus_amplitude_mm = 0.1      #   LensMesh, VitreousBody, LidMotion in
    [model.dynamics.lids]          #   [model.dynamics.accommodation], .lens, .vitreous,
    interval_s = 4.0               #   .lids)
    [output]
    npix = 512
    [spectrum]
    wavelengths_nm = "380:770:32"  # spectral = "scaled" only
    reference_wavelength_nm = 575.0
    illuminant = "E"
    colourspace = "sRGB"
    copy_weighting = "energy"      # each copy keeps the 575 nm PSF's energy; "paper": the
                                   #   paper's plain look-up, (lambda / 575)^2 of it
    ```

    **Raises:** `ConfigError` naming the key for unknown keys, wrong types or choices;
    `PhysicsRangeError` for values out of range.
    """
    check_sections(config, MODEL_SECTIONS, source)
    npix = square_npix(grid.npix, source)
    pixel_scale_deg, wavelengths_nm = grid.pixel_scale_deg, grid.wavelengths_nm
    model = Section(config.get("model", {}), "model")
    kind = model.get("kind", str, required=True)
    if kind != "temporal":
        raise ConfigError(f"model.kind = {kind!r}; temporal_from_config reads kind = 'temporal'")
    eye = eye_from_config(model.get("eye", dict, required=True), "model.eye", base_dir)
    dyn_table = Section(model.get("dynamics", dict, {}), "model.dynamics")
    classes = _part_classes()
    parts = {
        name: _read_part(classes[name], dyn_table.get(name, dict, {}), f"model.dynamics.{name}")
        for name in _DYNAMICS_PARTS
    }
    dyn_table.finish()
    if "seed" in model.table and "key_data" in model.table:
        raise ConfigError("model: give seed or key_data, not both")
    key_data = model.get("key_data", list, None)
    if key_data is not None:
        if not key_data or not all(isinstance(v, int) and 0 <= v < 2**32 for v in key_data):
            raise ConfigError(f"model.key_data must be a list of uint32 integers, got {key_data!r}")
        key: Any = jax.random.wrap_key_data(np.asarray(key_data, np.uint32))
    else:
        key = model.get("seed", int, 0)
    params = Section(model.get("tonemap_params", dict, {}), "model.tonemap_params")
    for name in params.table:
        params.get(name, float)
    kwargs = dict(
        focal_length_mm=model.get("focal_length_mm", float, EYE_FOCAL_LENGTH_MM),
        fresnel=model.choice("fresnel", FRESNEL_MODES, "retina"),
        fresnel_distance_mm=model.get("fresnel_distance_mm", float, None),
        aperture_npix=model.get("aperture_npix", int, None),
        window_mm=model.get("window_mm", float, None),
        fps=model.get("fps", float, 30.0),
        key=key,
        field_luminance_cd_m2=model.get("field_luminance_cd_m2", float, 100.0),
        luminance_scale=model.get("luminance_scale", float, 1.0),
        brightness=model.choice("brightness", BRIGHTNESS, "transmitted"),
        tonemap_name=model.get("tonemap", str, "gamma"),
        tonemap_params={k: float(v) for k, v in params.table.items()} or None,
    )
    model.finish()
    output = Section(config.get("output", {}), "output")
    out_npix = output.get("npix", int, 512)
    if output.get("pixel_scale_deg", float, None) is not None or pixel_scale_deg is not None:
        raise ConfigError(
            "the temporal model computes its PSF at the FFT's native pixel scale; drop "
            "output.pixel_scale_deg (frames at another scale get a resampled PSF)"
        )
    output.finish()
    spectrum = Section(config.get("spectrum", {}), "spectrum")
    lams = spectrum.get("wavelengths_nm", (float, list, str), DEFAULT_WAVELENGTHS)
    # One FFT per frame: the spectrum is made of scaled copies, so "exact" is refused.
    spectrum.choice("spectral", ("scaled",), "scaled")
    colour = dict(
        reference_wavelength_nm=spectrum.get("reference_wavelength_nm", float, 575.0),
        illuminant=spectrum.get("illuminant", str, "E"),
        colourspace=spectrum.get("colourspace", str, "sRGB"),
        copy_weighting=spectrum.choice("copy_weighting", COPY_WEIGHTINGS, "energy"),
    )
    spectrum.finish()
    with prefixed("spectrum.wavelengths_nm" if wavelengths_nm is None else "wavelengths"):
        parse_wavelengths(lams if wavelengths_nm is None else wavelengths_nm)
    out_npix = out_npix if npix is None else npix
    # One FFT per frame at the aperture raster's size: the scaled copies share it.
    check_psf_memory(
        source, aperture_npix=kwargs["aperture_npix"] or out_npix // 2, npix=out_npix,
        n_wavelengths=1, names="model.aperture_npix, output.npix",
    )  # fmt: skip
    return TemporalGlare.build(
        eye,
        EyeDynamics(**parts),
        npix=out_npix,
        wavelengths_nm=lams if wavelengths_nm is None else wavelengths_nm,
        **colour,
        **kwargs,
    )
