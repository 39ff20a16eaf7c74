"""The raster models' configs: kinds ``"aperture"``, ``"eye"`` and ``"camera"``.

Schema of a model config (every key but ``model.kind``, ``focal_length_mm`` and the
shapes has a default)::

    [model]
    kind = "aperture"             # "aperture", "eye" or "camera" (see below)
    focal_length_mm = 17.0        # pupil-to-retina / lens-to-sensor distance
    propagation = "fraunhofer"    # or "fresnel" (the E term of Ritschel et al., eq. 3)
    aperture_npix = 256           # raster size of the aperture window
    window_mm = 4.1               # default: the aperture's extent plus 2 px each side
    method = "auto"               # "fft", "mft", "auto", "quad" or "polygon"

    [model.quad]                  # only with method = "quad" (every key optional)
    base_level = 0                # 1: the paper's half-size quadtree (approximate)
    band = 0                      # pixels around soft edges kept as single quads (-1: none)
    symmetry = "auto"             # skip the odd parts of a mirror-symmetric aperture
    cull_below = 0.0              # skip tiles below this fraction of the peak (sec. 4.3)

    [model.polygon]               # only with method = "polygon"
    arc_segments = 16             # chords per arc of a rounded blade or capsule end

    [[model.shapes]]              # union of "open" shapes times all "block" shapes
    kind = "disk"                 # disk, ellipse, polygon, capsule, image
    diameter_mm = 4.0

    [output]
    npix = 512
    pixel_scale_deg = 0.0004      # default: the FFT's native scale (fast path)

    [spectrum]
    wavelengths_nm = 550          # a number, a list, or "380:770:32"
    spectral = "exact"            # "scaled" (copies of the reference PSF), or the
                                  # near-field approximation "near_field_heuristic"
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
    wide_angle = "ensemble"       # an eye's particles beyond the raster's band: "ensemble",
                                  #   "phases" (with their positions) or "none"

    [model.eye]                   # see invglare.config.eye.eye_from_config
    seed = 7
    [model.eye.pupil]
    diameter_mm = 3.0

    [model.camera]                # kind = "camera": invglare.config.camera.camera_from_config
    [model.camera.diaphragm]
    n_blades = 6
    f_number = 8.0
    focal_length_mm = 50.0

The kind ``"veiling"`` (lens ghosts as Fourier series, :mod:`invglare.config.veiling`)
has its own schema; see ``examples/veiling_cooke.toml``. The kind ``"temporal"`` (the dynamic
eye of Ritschel et al., :func:`invglare.config.temporal.temporal_from_config`) likewise; see
``examples/temporal_eye.toml``.

Without ``[spectrum] wavelengths_nm`` a spectral model uses 380:770:32 and a paper_rgb
model 680/530/460 nm; one wavelength gives a monochrome PSF (what a fit needs).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from invglare._core.memory import check_psf_memory
from invglare.aperture import Aperture
from invglare.config.camera import camera_from_config
from invglare.config.eye import eye_from_config
from invglare.config.section import MODEL_SECTIONS, Section, check_sections
from invglare.config.shapes import shape_from_config
from invglare.errors import ConfigError, prefixed
from invglare.models.aperture_psf import AperturePSF
from invglare.models.kakimoto import COLOURS, MASKINGS, WIDE_ANGLE, KakimotoGlare
from invglare.optics.propagator import METHODS, PROPAGATIONS
from invglare.optics.spectral import SPECTRAL_METHODS, parse_wavelengths


@dataclasses.dataclass(frozen=True)
class GridRequest:
    """What a caller asks of a model's grid, over the config's own values (None: keep).

    - `npix`: output size, one integer or ``(ny, nx)`` (a fit asks for its photo's).
    - `pixel_scale_deg`: degrees per output pixel.
    - `wavelengths_nm`: the wavelengths (a number, a list, or ``"380:770:32"``).
    """

    npix: int | tuple[int, int] | None = None
    pixel_scale_deg: float | None = None
    wavelengths_nm: Any = None


#: A request that keeps the config's own grid and wavelengths.
KEEP_GRID = GridRequest()

#: The kinds this reader builds.
RASTER_KINDS = ("aperture", "eye", "camera")
def square_npix(npix: int | tuple[int, int] | None, source: str) -> int | None:
    """A PSF model's output size from an override that may be a square ``(n, n)``."""
    if npix is None or isinstance(npix, int):
        return npix
    ny, nx = (int(v) for v in npix)
    if ny != nx:
        raise ConfigError(
            f"{source}: this model's PSF is square; an image of {ny}x{nx} pixels needs a "
            "square crop"
        )
    return ny


#: The keys of each method's own table and their types.
_OPTION_KEYS = {
    "quad": {"base_level": int, "band": int, "symmetry": str, "cull_below": float, "tile": int},
    "polygon": {"arc_segments": int, "band": int},
}


def method_options(model: Section, method: str) -> dict[str, Any] | None:
    """The ``[model.quad]`` or ``[model.polygon]`` table of the chosen method (or None).

    A method's table under another method is refused: it would be silently ignored.
    """
    chosen = None
    for name, keys in _OPTION_KEYS.items():
        table = model.section(name)
        if table is None:
            continue
        if name != method:
            raise ConfigError(
                f"[model.{name}] sets options of method = {name!r}, but method = {method!r}"
            )
        chosen = {key: table.get(key, kind, None) for key, kind in keys.items()}
        table.finish()
    return None if chosen is None else {k: v for k, v in chosen.items() if v is not None}


def read_raster_model(
    config: dict[str, Any],
    base_dir: str | Path | None = None,
    grid: GridRequest = KEEP_GRID,
    source: str = "config",
) -> AperturePSF | KakimotoGlare:
    """The model of a config of kind ``"aperture"``, ``"eye"`` or ``"camera"``.

    `grid` overrides the config's output grid and wavelengths; its `npix` may be
    ``(n, n)`` (the grid of a square photo). See the module docstring for the schema.
    """
    check_sections(config, MODEL_SECTIONS, source)
    npix = square_npix(grid.npix, source)
    pixel_scale_deg, wavelengths_nm = grid.pixel_scale_deg, grid.wavelengths_nm
    model = Section(config["model"], "model")
    kind = model.choice("kind", RASTER_KINDS, "aperture")
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
            aperture = eye_from_config(table, "model.eye", base_dir)
            focal = model.get("focal_length_mm", float, 17.0)
            distance = model.get("obstacle_distance_mm", float, 8.0)
        else:
            aperture = camera_from_config(table, "model.camera", base_dir)
            focal = model.get("focal_length_mm", float, None)
            if focal is None:
                focal = float(aperture.diaphragm.focal_length_mm)
            distance = model.get("obstacle_distance_mm", float, 0.0)
        glare = dict(
            obstacle_distance_mm=distance,
            masking=model.choice("masking", MASKINGS, "fixed"),
            colour=model.choice("colour", COLOURS, "spectral"),
            max_light_angle_deg=model.get("max_light_angle_deg", float, 0.0),
            wide_angle=model.choice("wide_angle", WIDE_ANGLE, "ensemble"),
        )
    sampling = dict(
        propagation=model.choice("propagation", PROPAGATIONS, "fraunhofer"),
        aperture_npix=model.get("aperture_npix", int, 256),
        window_mm=model.get("window_mm", float, None),
        method=model.choice("method", METHODS, "auto"),
    )
    sampling["method_options"] = method_options(model, sampling["method"])
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
    if lams is not None:
        with prefixed("spectrum.wavelengths_nm" if wavelengths_nm is None else "wavelengths"):
            lams = parse_wavelengths(lams)
    check_psf_memory(
        source, aperture_npix=sampling["aperture_npix"], npix=sampling["npix"],
        n_wavelengths=1 if lams is None else len(lams),
        names="model.aperture_npix, output.npix, spectrum.wavelengths_nm",
    )  # fmt: skip

    if kind == "aperture":
        return AperturePSF.build(
            aperture, focal_length_mm=focal, wavelengths_nm=lams, **sampling, **colour
        )
    return KakimotoGlare.build(
        aperture, focal_length_mm=focal, wavelengths_nm=lams, **glare, **sampling, **colour
    )
