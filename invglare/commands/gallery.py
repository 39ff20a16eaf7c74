"""``invglare gallery``: aperture, PSF and a rendered scene for a few eyes and cameras.

One PNG row per model: the aperture transmission ``|t_o P|`` (mm), the PSF as
``log10(PSF / peak)`` from -6 to 0 (luminance of an RGB PSF; degrees), and a bundled
procedural scene convolved with the PSF and tone-mapped. ``runs/gallery.md`` lists
them; the PNGs go to ``runs/gallery/`` (replaced as a whole, atomically). ``--out-dir
reports`` refreshes the committed gallery.
"""

from __future__ import annotations

import copy
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from invglare.errors import ConfigError

log = logging.getLogger("invglare")

#: Kinds of model config the gallery shows (the Kakimoto eye and camera).
GALLERY_KINDS = ("eye", "camera")
#: Few wavelengths: the PSFs are RGB but cheap.
DEFAULT_WAVELENGTHS_NM = "400:700:8"
#: The scene's pixels, in PSF pixels: the eye and camera PSFs span under a degree, so at a
#: scene's own 0.05 deg/px their streaks would cover a few pixels; "scene" keeps that scale.
DEFAULT_SCENE_SCALE = "2"
#: log10 range of the PSF panel.
LOG_FLOOR = -6.0


@dataclass(frozen=True)
class GalleryEntry:
    """One row of the gallery: a model config (possibly edited in memory) and its caption."""

    name: str
    path: Path
    config: dict[str, Any]
    note: str


def _examples_dir() -> Path:
    """``examples/`` of the checkout (the gallery's defaults live there)."""
    return Path(__file__).resolve().parents[2] / "examples"


def _first_sentence(path: Path) -> str:
    """The first sentence of the leading comment block of a TOML file ("" if none)."""
    words: list[str] = []
    for line in path.read_text(encoding="utf-8").splitlines():
        if not line.startswith("#"):
            break
        words.append(line.lstrip("#").strip())
    text = " ".join(w for w in words if w)
    end = text.find(". ")
    return text if end < 0 else text[: end + 1]


def _entry(path: Path, name: str | None = None, note: str | None = None) -> GalleryEntry:
    from invglare.files.toml import load_toml

    config = load_toml(path)
    kind = config.get("model", {}).get("kind")
    if kind not in GALLERY_KINDS:
        raise ConfigError(
            f"{path}: model.kind = {kind!r}; the gallery shows {' and '.join(GALLERY_KINDS)} models"
        )
    return GalleryEntry(name or path.stem, path, config, note or _first_sentence(path))


def default_entries() -> list[GalleryEntry]:
    """Daylight vs night eye, lashes vs none, a 6-blade camera with and without a cross screen."""
    ex = _examples_dir()
    day = _entry(
        ex / "eye_daylight.toml",
        note="Daylight eye: 3 mm pupil, narrowed lids, upper lashes and cornea cells. The "
        "near-vertical lashes spread light sideways into a fan of streaks; the straight lid "
        "edges make the vertical streak.",
    )
    night = _entry(
        ex / "eye_night.toml",
        note="Night eye: 6.5 mm pupil, open lids, lens and vitreous particles and lens-fibre "
        "gratings: a veil around the core and the coloured lenticular halo ring (about "
        "0.2 deg).",
    )
    no_lashes = copy.deepcopy(day.config)
    eye = no_lashes["model"]["eye"]
    for key in [k for k in eye if k.startswith("lashes")]:
        del eye[key]
    cross = _entry(
        ex / "camera_cross_screen.toml",
        note="Camera, 50 mm f/8, 6-blade diaphragm behind a cross-screen filter: six blade "
        "spikes plus the filter's cross of diffraction orders.",
    )
    blades = copy.deepcopy(cross.config)
    del blades["model"]["camera"]["cross_screen"]
    return [
        day,
        night,
        GalleryEntry(
            "eye_daylight_no_lashes",
            day.path,
            no_lashes,
            "The daylight eye with its lash tables removed: the sideways fan of lash streaks "
            "goes; the lids' vertical streak and the pupil's Airy rings remain.",
        ),
        cross,
        GalleryEntry(
            "camera_6_blades",
            cross.path,
            blades,
            "The same camera without the cross-screen filter: only the six diffraction spikes "
            "of the hexagonal stop.",
        ),
    ]


def _unique_names(entries: list[GalleryEntry]) -> list[GalleryEntry]:
    seen: dict[str, int] = {}
    out = []
    for e in entries:
        n = seen.get(e.name, 0) + 1
        seen[e.name] = n
        out.append(e if n == 1 else GalleryEntry(f"{e.name}_{n}", e.path, e.config, e.note))
    return out


def _resample(psf, own_scale: float, scale_deg: float, max_npix: int):
    """``psf_at_scale`` on a PSF already computed (the gallery shows it, so it is computed once)."""
    from invglare.render.convolve import resample_psf

    if math.isclose(own_scale, scale_deg, rel_tol=1e-6):
        return psf
    npix = min(max_npix, max(3, math.ceil(psf.shape[0] * own_scale / scale_deg)))
    npix += 1 - npix % 2
    return resample_psf(psf, own_scale, scale_deg, npix)


def _fit_aperture_npix(entry: GalleryEntry, npix: int, wavelengths_nm) -> GalleryEntry:
    """`entry` with ``aperture_npix`` raised where the new spectrum's shortest wavelength needs it.

    A config sampled for 550 nm may alias at 400 nm (its PSF field reaches past
    ``lambda / (2 pitch)``); a finer raster of the same window keeps it alias-free.
    """
    from invglare.config.model import build_model
    from invglare.optics.spectral import parse_wavelengths

    if wavelengths_nm is None:
        return entry
    shortest_nm = float(np.min(parse_wavelengths(wavelengths_nm)))
    own = build_model(entry.config, base_dir=entry.path.parent, npix=npix, source=str(entry.path))
    grid, output = own.propagator.grid, own.propagator.output
    half_field_rad = math.radians(float(output.half_field_deg))
    max_pitch_mm = shortest_nm * 1e-6 / (2 * half_field_rad)
    needed = math.ceil(float(grid.width_mm) / max_pitch_mm / 8) * 8
    if needed <= grid.npix:
        return entry
    config = copy.deepcopy(entry.config)
    config["model"]["aperture_npix"] = needed
    note = (
        f"{entry.note} (aperture_npix raised from {grid.npix} to {needed} for {shortest_nm:g} nm.)"
    )
    return GalleryEntry(entry.name, entry.path, config, note)


def _row(
    entry: GalleryEntry,
    scene_img,
    scene_scale: float,
    npix: int,
    wavelengths_nm,
    png: Path,
):
    """Build the model, compute aperture / PSF / glare image and save one PNG row.

    `scene_scale`: the scene's deg/px if > 0, else ``-k``: k times the PSF's pixel scale.
    """
    import jax
    import jax.numpy as jnp
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from invglare.config.model import build_model
    from invglare.render import convolve_psf, luminance, tonemap

    model = build_model(
        entry.config,
        base_dir=entry.path.parent,
        npix=npix,
        wavelengths_nm=wavelengths_nm,
        source=str(entry.path),
    )
    grid = model.propagator.grid
    aperture = np.abs(np.asarray(jax.jit(lambda m: m.field())(model)))
    psf = jax.jit(lambda m: m())(model)
    own_scale = float(model.pixel_scale_deg)
    lum = np.asarray(luminance(psf), dtype=np.float64)
    log_psf = np.log10(np.maximum(lum / lum.max(), 10.0**LOG_FLOOR))

    if scene_scale <= 0:
        scene_scale = -scene_scale * own_scale
    small = _resample(psf, own_scale, scene_scale, max_npix=2 * max(scene_img.shape[:2]) + 1)
    if small.ndim == 2:
        small = jnp.repeat(small[..., None], scene_img.shape[2], axis=-1)
    # A spectral PSF has out-of-gamut (negative) sRGB components; the tone map needs
    # non-negative luminance, so they are clipped after the convolution.
    glare = jnp.maximum(convolve_psf(jnp.asarray(scene_img), small), 0.0)
    shown = np.clip(np.asarray(tonemap(glare, "reinhard")), 0.0, 1.0)

    half_mm = float(grid.pitch_mm) * grid.npix / 2
    half_deg = own_scale * psf.shape[0] / 2
    half_scene = scene_scale * scene_img.shape[0] / 2
    fig, axes = plt.subplots(1, 3, figsize=(14.0, 4.6), dpi=100, layout="constrained")
    im = axes[0].imshow(
        aperture, cmap="gray", vmin=0, extent=(-half_mm, half_mm, half_mm, -half_mm)
    )
    axes[0].set(title="aperture |t_o P|", xlabel="x (mm)", ylabel="y (mm)")
    fig.colorbar(im, ax=axes[0], shrink=0.85)
    im = axes[1].imshow(
        log_psf,
        cmap="inferno",
        vmin=LOG_FLOOR,
        vmax=0.0,
        extent=(-half_deg, half_deg, half_deg, -half_deg),
    )
    what = "luminance" if psf.ndim == 3 else "PSF"
    axes[1].set(title=f"log10({what} / peak)", xlabel="x (deg)", ylabel="y (deg)")
    fig.colorbar(im, ax=axes[1], shrink=0.85)
    axes[2].imshow(shown, extent=(-half_scene, half_scene, half_scene, -half_scene))
    axes[2].set(title="scene with glare (Reinhard)", xlabel="x (deg)", ylabel="y (deg)")
    fig.suptitle(entry.name)
    fig.savefig(png)
    plt.close(fig)


def _display_path(path: Path) -> str:
    try:
        return Path(os.path.relpath(path.resolve(), Path.cwd())).as_posix()
    except ValueError:  # another drive on Windows
        return path.as_posix()


def _markdown(
    entries: list[GalleryEntry],
    scene: str,
    npix: int,
    wavelengths_nm,
    scene_scale: str,
    scene_px_deg: float,
) -> str:
    spectrum = "the configs' own wavelengths" if wavelengths_nm is None else f"{wavelengths_nm} nm"
    if scene_scale == "scene":
        placed = f"at its own {scene_px_deg:g} deg/px (the PSF area-averaged onto its pixels)"
    else:
        placed = (
            f"with pixels of {scene_scale} x the PSF's pixel scale instead of its own "
            f"{scene_px_deg:g} deg/px (as if seen from further away: the PSFs span under a "
            "degree, so at the scene's own scale their streaks would cover a few pixels)"
        )
    lines = [
        "# Gallery: eyes and cameras",
        "",
        "Made by `invglare gallery`. Each row: the aperture transmission |t_o P| (axes in mm), "
        "the PSF as log10(PSF / peak) from -6 to 0 (luminance of the RGB PSF; axes in degrees), "
        f"and the bundled scene `{scene}` ({npix} x {npix}) {placed}, convolved with the PSF "
        f"(FFT) and tone-mapped (Reinhard). PSFs: {npix} x {npix} pixels at each config's own "
        f"pixel scale, spectral over {spectrum}. With few wavelengths a dispersed "
        "diffraction order shows as separate coloured spots; out-of-gamut (negative) sRGB "
        "values are clipped before tone mapping.",
        "",
    ]
    for e in entries:
        lines += [
            f"## {e.name}",
            "",
            f"Config: `{_display_path(e.path)}`"
            + ("" if e.name == e.path.stem else ", edited in memory as described below"),
            "",
            e.note,
            "",
            f"![{e.name}](gallery/{e.name}.png)",
            "",
        ]
    return "\n".join(lines)


def _scene_factor(scene_scale: str) -> float | None:
    """None for "scene", else the positive multiple of the PSF's pixel scale."""
    if scene_scale == "scene":
        return None
    try:
        factor = float(scene_scale)
    except ValueError:
        factor = math.nan
    if not (math.isfinite(factor) and factor > 0):
        raise ConfigError(
            f"--scene-scale must be 'scene' or a positive multiple of the PSF's pixel scale, "
            f"got {scene_scale!r}"
        )
    return factor


def run_gallery(
    models: list[Path] | None,
    out_dir: Path,
    scene: str = "street_lights_at_night",
    npix: int = 256,
    wavelengths_nm: str | None = DEFAULT_WAVELENGTHS_NM,
    scene_scale: str = DEFAULT_SCENE_SCALE,
) -> Path:
    """Write ``out_dir/gallery.md`` and ``out_dir/gallery/<name>.png``; return the md path.

    `models`: eye / camera configs (TOML); empty or None for the default list.
    `wavelengths_nm`: overrides every config's spectrum (None keeps the configs').
    `scene_scale`: a number k gives the scene pixels of k times each PSF's pixel scale
    (the glare is then visible); ``"scene"`` keeps the scene's own deg/px (the PSF is
    area-averaged onto it).
    """
    from tqdm import tqdm

    from invglare.commands import options
    from invglare.files.atomic import atomic_directory, atomic_write
    from invglare.files.outputs import output_file, output_folder
    from invglare.render.scenes import SCENES

    if scene not in SCENES:
        raise ConfigError(f"unknown scene {scene!r}; bundled scenes: {', '.join(SCENES)}")
    factor = _scene_factor(scene_scale)
    if npix < 16:
        raise ConfigError(f"--npix must be >= 16, got {npix}")
    options.raster(npix, "--npix", channels=3, copies=4)
    if wavelengths_nm is not None:
        options.wavelengths(wavelengths_nm)
    output_folder(Path(out_dir) / "gallery", "--out-dir", replaced=True)
    output_file(Path(out_dir) / "gallery.md", "--out-dir", (".md",))
    entries = _unique_names([_entry(Path(p)) for p in models] if models else default_entries())
    scene_img, scene_px_deg = SCENES[scene](npix=npix, seed=0)
    scene_img = np.asarray(scene_img)
    out_dir = Path(out_dir)
    with atomic_directory(out_dir / "gallery") as tmp:
        for i, entry in enumerate(tqdm(entries, desc="gallery", unit="model", disable=None)):
            entry = entries[i] = _fit_aperture_npix(entry, npix, wavelengths_nm)
            _row(
                entry,
                scene_img,
                float(scene_px_deg) if factor is None else -factor,
                npix,
                wavelengths_nm,
                tmp / f"{entry.name}.png",
            )
    md = out_dir / "gallery.md"
    text = _markdown(entries, scene, npix, wavelengths_nm, scene_scale, float(scene_px_deg))
    atomic_write(md, lambda p: p.write_text(text, encoding="utf-8"))
    log.info("wrote %s and %d PNGs in %s", md, len(entries), out_dir / "gallery")
    return md
