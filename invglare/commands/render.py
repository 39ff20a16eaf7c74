"""``invglare render`` and ``invglare scene``: glare on an HDR image, and the bundled scenes."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from invglare.errors import ConfigError, InputDataError
from invglare.files.outputs import output_file, output_folder

log = logging.getLogger("invglare")

MODES = ("convolve", "billboard", "kakimoto")
OUTPUT_SUFFIXES = (".exr", ".png")
#: Animation outputs: a video, a GIF, or (no suffix) a folder of linear EXR frames.
ANIMATION_SUFFIXES = (".mp4", ".gif")
#: Frames rendered per compiled call of an animation (one compilation, a steady progress bar).
ANIMATION_CHUNK = 8


#: The smallest scene (the procedural lights need a few pixels to be drawn).
MIN_SCENE_NPIX = 8


def run_scene(name: str, out: Path, npix: int, seed: int, depth: Path | None = None) -> None:
    from invglare.commands import options
    from invglare.files.outputs import output_file
    from invglare.render.scenes import SCENES, write_scene

    if name not in SCENES:
        raise ConfigError(f"unknown scene {name!r}; bundled scenes: {', '.join(SCENES)}")
    out = output_file(out, "--out", (".exr",))
    if depth is not None:
        depth = output_file(depth, "--depth", (".exr",))
    options.count(npix, "--npix", MIN_SCENE_NPIX)
    options.count(seed, "--seed", 0)
    options.raster(npix, "--npix", channels=3, copies=3)
    write_scene(name, out, npix=npix, seed=seed, depth_path=depth)
    log.info("wrote %s (%s, %dx%d, linear cd/m^2)", out, name, npix, npix)
    if depth is not None:
        log.info("wrote %s (its depth buffer: Z, planar metres)", depth)


def psf_at_scale(model, scale_deg: float, max_npix: int):
    """The model's PSF resampled (energy-preserving) to `scale_deg` per pixel.

    The PSF is computed at the model's own sampling, which resolves the
    diffraction pattern, and then area-averaged onto the image's coarser pixels.
    """
    import jax

    from invglare._core.memory import check_compiled_memory
    from invglare.render.convolve import resample_psf
    from invglare.render.position_glare import psf_npix_at_scale

    compiled = jax.jit(lambda m: m()).lower(model).compile()
    check_compiled_memory(compiled, f"the PSF of a {type(model).__name__}")
    psf = compiled(model)
    own_scale = float(model.pixel_scale_deg)
    if math.isclose(own_scale, scale_deg, rel_tol=1e-6):
        return psf
    npix = psf_npix_at_scale(psf.shape[0], own_scale, scale_deg, max_npix)
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
    frames: int | None = None,
    fps: float | None = None,
    iterations: int | None = None,
    depth: Path | None = None,
    seed: int = 0,
) -> None:
    from invglare.config.section import precheck_model_config

    config = precheck_model_config(model_path)  # a typo is reported before JAX loads
    import jax.numpy as jnp

    from invglare.render import convolve_psf, replace_with_billboards

    _check_render_options(mode, threshold, max_bright, tonemap_name, exposure, pixel_scale_deg)
    if frames is not None or fps is not None:
        run_animation(scene, model_path, out, frames, fps, pixel_scale_deg)
        return
    if iterations is not None or depth is not None:
        run_scene_render(scene, model_path, out, tonemap_name, exposure, iterations, depth, seed)
        return
    out = output_file(out, "--out", OUTPUT_SUFFIXES)
    image, scale = _read_scene_and_scale(scene, pixel_scale_deg)
    # A model whose image covers the screen (lens ghosts) is built on the scene's grid,
    # with its axis at the centre; a PSF model at its own sampling.
    model = _load_model(
        model_path,
        config=config,
        grid_of=lambda kind: (
            dict(npix=tuple(image.shape[:2]), pixel_scale_deg=scale)
            if kind.model_class.centre == "axis"
            else {}
        ),
    )
    if model.renders_scenes:
        run_scene_render(scene, model_path, out, tonemap_name, exposure, None, None, seed, model)
        return
    if model.centre == "axis":
        from invglare.render.ghost_frames import render_ghosts

        bright = _bright(jnp.asarray(image), threshold, max_bright)
        result = render_ghosts(model, image, bright, scale)
        params = _tonemap_params(out, tonemap_name, exposure)
        _write(out, np.asarray(result), scale, model, "ghosts", scene, tonemap_name, params)
        return
    max_npix = 2 * max(image.shape[:2]) + 1
    if mode == "kakimoto":
        run_kakimoto_composite(
            image, model, out, scale, scene, threshold, max_bright, tonemap_name, exposure
        )
        return
    if not model.shift_invariant:
        # Each light gets the PSF of its own direction (Kakimoto eq. 3: the lashes move
        # with the light), which a convolution cannot do.
        if mode != "billboard":
            raise ConfigError(
                f"{model_path} depends on the light's direction (e.g. masking = 'position'): "
                "each light gets its own PSF, which a convolution cannot do; render it with "
                "--mode billboard"
            )
        from invglare.render.position_glare import render_position_glare

        bright = _bright(jnp.asarray(image), threshold, max_bright)
        result = render_position_glare(model, image, bright, scale, max_npix)
        # The on-axis PSF sets the exposure of the kakimoto tone map.
        params = _tonemap_params(out, tonemap_name, exposure, model, image, scale, max_npix)
        _write(out, np.asarray(result), scale, model, "billboard", scene, tonemap_name, params)
        return
    psf = psf_at_scale(model, scale, max_npix=max_npix)
    params = _tonemap_params(out, tonemap_name, exposure, model, image, scale, max_npix, psf)
    if image.ndim == 3 and psf.ndim == 2:
        psf = jnp.repeat(psf[..., None], image.shape[2], axis=-1)
    if image.ndim == 2 and psf.ndim == 3:
        raise InputDataError(f"{scene} is monochrome (Y) but the model's PSF is RGB")
    image = jnp.asarray(image)
    if mode == "convolve":
        result = convolve_psf(image, psf)
    else:
        # Listed bright pixels are replaced by their spread light, so energy is conserved;
        # bright pixels beyond max_bright stay as they are.
        result = replace_with_billboards(image, _bright(image, threshold, max_bright), psf)
    _write(out, np.asarray(result), scale, model, mode, scene, tonemap_name, params)
    log.info("PSF %dpx at %.4g deg/px", psf.shape[0], scale)


def _check_render_options(
    mode: str,
    threshold: float | None,
    max_bright: int,
    tonemap_name: str,
    exposure: float,
    pixel_scale_deg: float | None,
) -> None:
    """The options every kind of render takes, checked before anything is read."""
    from invglare.commands import options
    from invglare.render.tonemap import TONEMAPS

    if mode not in MODES:
        raise ConfigError(f"--mode {mode!r} is not one of {', '.join(MODES)}")
    if tonemap_name not in TONEMAPS:
        raise ConfigError(f"--tonemap {tonemap_name!r} is not one of {', '.join(TONEMAPS)}")
    options.positive(threshold, "--threshold", zero=True)
    options.count(max_bright, "--max-bright")
    options.positive(exposure, "--exposure")
    options.positive(pixel_scale_deg, "--pixel-scale-deg")


def _read_scene(scene: Path):
    """The scene's EXR (a missing, unreadable or non-EXR file is one line naming it)."""
    from invglare.files.exr import read_exr

    if scene.suffix.lower() != ".exr":
        raise InputDataError(f"scene {str(scene)!r} is not an OpenEXR file (.exr)")
    if scene.is_dir():
        raise InputDataError(f"scene {str(scene)!r} is a folder, not an EXR file")
    if not scene.exists():
        raise InputDataError(f"scene {str(scene)!r} does not exist")
    return read_exr(scene)


def _read_scene_and_scale(scene: Path, pixel_scale_deg: float | None):
    """The scene's checked image and its degrees per pixel (`pixel_scale_deg`, else its
    header's): a still render and an animation read a scene the same way."""
    from invglare.render import validate_scene

    img = _read_scene(scene)
    image = validate_scene(img.data, name=str(scene))
    scale = pixel_scale_deg if pixel_scale_deg is not None else img.pixel_scale_deg
    if scale is None:
        raise InputDataError(
            f"{scene} has no pixelScaleDeg header; pass --pixel-scale-deg (degrees per pixel)"
        )
    return image, scale


def run_kakimoto_composite(
    image,
    model,
    out: Path,
    scale: float,
    scene: Path,
    threshold,
    max_bright,
    tonemap_name,
    exposure,
) -> None:
    """Kakimoto et al.'s compositing (`invglare.render.composite`): the scene tone-mapped
    (``--tonemap``, ``--exposure``) with a sigmoid-mapped glare billboard blended on at each
    bright pixel, scaled by its value; a position-dependent model gives each its own."""
    import jax
    import jax.numpy as jnp

    from invglare.render import tonemap
    from invglare.render.composite import kakimoto_composite

    image = jnp.asarray(image)
    bright = _bright(image, threshold, max_bright)
    max_npix = 2 * max(image.shape[:2]) + 1
    core = model.core_radius_px()
    radius = 0.0 if core is None else core * float(model.pixel_scale_deg) / scale
    if model.shift_invariant:
        psf, index = psf_at_scale(model, scale, max_npix=max_npix), None
    else:
        from invglare.render.bright import light_angles_deg
        from invglare.render.position_glare import position_psf_bank, psf_npix_at_scale

        angles = light_angles_deg(bright, image.shape[:2], scale)
        own_npix = jax.eval_shape(lambda m: m(), model).shape[0]
        npix = psf_npix_at_scale(own_npix, float(model.pixel_scale_deg), scale, max_npix)
        psf = position_psf_bank(model, angles, scale, npix)
        index = jnp.arange(angles.shape[0])
    if image.ndim == 2 and psf.ndim == (3 if index is None else 4):
        raise InputDataError(f"{scene} is monochrome (Y) but the model's PSF is RGB")
    params = {"exposure": exposure} if tonemap_name in ("gamma", "srgb") else {}
    if tonemap_name == "kakimoto":
        raise ConfigError(
            "--mode kakimoto tone-maps each glare billboard by the sigmoid itself; choose the "
            "scene's tone map with --tonemap reinhard, gamma or srgb"
        )
    ldr = tonemap(image, tonemap_name, **params)
    result = kakimoto_composite(ldr, bright, psf, radius, psf_index=index)
    _write_display(out, np.asarray(result), scale, model, scene)
    log.info(
        "kakimoto compositing: %d billboards, spot radius %.3g px", int(bright.valid.sum()), radius
    )


def _write_display(out: Path, result, scale: float, model, scene: Path) -> None:
    """Display values (already composited): a PNG as they are, an EXR holding them."""
    from invglare.files.images import write_png

    if out.suffix.lower() == ".exr":
        attrs = {"renderMode": "kakimoto", "scene": str(scene), "values": "display [0, 1]"}
        _write_exr(out, result, scale, model, attrs)
    else:
        write_png(out, result)


def _write_exr(out: Path, result, scale: float, model, attrs: dict) -> None:
    """A rendered image as EXR: every render's file carries its scale and model config."""
    from invglare.files.exr import write_exr

    write_exr(out, result, pixel_scale_deg=scale, config=model.to_config(), attrs=attrs)


def _tonemap_params(
    out: Path,
    name: str,
    exposure: float,
    model=None,
    image=None,
    scale_deg=None,
    max_npix=None,
    psf=None,
) -> dict:
    """Keyword arguments of the PNG tone map (none for an EXR, which stays linear).

    For ``kakimoto`` with an eye or camera model, the central spot is its own layer
    (Kakimoto sec. 3.3): the exposure puts the brightest light's glare plateau at
    display white (`kakimoto_scene_scale`) and the spot saturates above it.
    """
    if out.suffix.lower() != ".png":
        return {}
    if name in ("gamma", "srgb"):
        return {"exposure": exposure}
    core = None if name != "kakimoto" or model is None else model.core_radius_px()
    if core is None:
        return {}
    from invglare.render import kakimoto_scene_scale

    if psf is None:
        psf = psf_at_scale(model, scale_deg, max_npix)
    radius = core * float(model.pixel_scale_deg) / scale_deg
    light = float(np.max(image))
    tonemap_scale = float(kakimoto_scene_scale(psf, radius, light))
    log.info(
        "kakimoto tone map: spot radius %.3g px; the glare of the brightest light (%.4g) "
        "reaches white (scale %.4g)",
        radius,
        light,
        tonemap_scale,
    )
    return {"scale": tonemap_scale}


def _write(out: Path, result, scale: float, model, mode: str, scene: Path, tonemap_name, params):
    """A linear EXR (model config in the header) or a tone-mapped PNG."""
    from invglare.files.images import write_png
    from invglare.render import tonemap

    if out.suffix.lower() == ".exr":
        _write_exr(out, result, scale, model, {"renderMode": mode, "scene": str(scene)})
    else:
        write_png(out, np.asarray(tonemap(result, tonemap_name, **params)))
    log.info("wrote %s (%s)", out, mode)


def _load_model(model_path: Path, grid_of=None, config=None):
    """The model of a config file; `grid_of(kind)` gives ``npix`` / ``pixel_scale_deg``
    overrides for a registered model kind; `config` is the file already read (and checked,
    :func:`~invglare.config.section.precheck_model_config`), else it is read here."""
    from invglare.config.section import precheck_model_config

    config = precheck_model_config(model_path) if config is None else config
    from invglare.config.model import build_model, config_kind

    grid = grid_of(config_kind(config, str(model_path))) if grid_of is not None else {}
    return build_model(config, base_dir=model_path.parent, source=str(model_path), **grid)


def _bright(image, threshold: float | None, max_bright: int):
    """The lights: the `max_bright` brightest pixels above `threshold` (default max / 100)."""
    import jax.numpy as jnp

    from invglare._core.colour import rec709_luminance
    from invglare.render import bright_pixel_list

    lum = image if image.ndim == 2 else rec709_luminance(image)
    brightest = float(jnp.max(lum))
    if brightest <= 0:
        raise InputDataError(
            "the scene is dark (its brightest pixel is 0): there is no light to give glare"
        )
    level = brightest / 100.0 if threshold is None else threshold
    bright = bright_pixel_list(image, level, max_bright)
    if int(bright.n_above) > max_bright:
        log.warning(
            "%d pixels exceed the threshold %.4g; only the %d brightest get glare "
            "(raise --max-bright or --threshold)",
            int(bright.n_above),
            level,
            max_bright,
        )
    return bright


def _animation_target(out: Path) -> str:
    """ "mp4", "gif" or "exr" (a folder of frames) from the output path, or a ConfigError."""
    suffix = out.suffix.lower()
    if suffix and suffix not in ANIMATION_SUFFIXES:
        raise ConfigError(
            f"an animation's --out must end in {' or '.join(ANIMATION_SUFFIXES)}, or be a "
            f"folder (no suffix) for EXR frames; got {out.name!r}"
        )
    if suffix:
        output_file(out, "--out", ANIMATION_SUFFIXES)
        return suffix[1:]
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ConfigError(f"--out folder {str(out)!r} exists and is not empty; choose a new one")
    output_folder(out, "--out")
    return "exr"


def _frame_writer(target: str, path: Path, fps: float):
    """An imageio writer for 8-bit frames (mp4 through imageio-ffmpeg's bundled encoder)."""
    import imageio.v2 as imageio

    if target == "mp4":
        try:
            import imageio_ffmpeg  # noqa: F401  (the encoder imageio's ffmpeg plugin runs)
        except ImportError:
            raise ConfigError(
                "writing .mp4 needs the imageio-ffmpeg package (pip install imageio-ffmpeg); "
                "or write a .gif or a folder of EXR frames"
            ) from None
        # macro_block_size 2: yuv420p needs even sizes, and anything coarser rescales frames.
        return imageio.get_writer(
            path, format="FFMPEG", fps=fps, codec="libx264", quality=8, macro_block_size=2
        )
    return imageio.get_writer(path, format="GIF", mode="I", duration=1000.0 / fps, loop=0)


def _check_animation_size(target: str, out: Path, frames: int, image) -> None:
    """Refuse --frames that cannot be stored: EXR frames on the disk, a GIF in memory
    (its writer keeps every frame until it closes)."""
    from invglare._core.memory import check_memory
    from invglare.files.outputs import check_disk

    h, w = image.shape[:2]
    what = f"{frames} frames of {w}x{h} pixels (--frames {frames})"
    if target == "exr":
        check_disk(float(frames) * h * w * 3 * 4, out, what)
    elif target == "gif":
        check_memory(float(frames) * h * w * 3, f"a GIF of {what}")


def run_animation(
    scene: Path,
    model_path: Path,
    out: Path,
    frames: int | None,
    fps: float | None,
    pixel_scale_deg: float | None,
) -> None:
    """``invglare render --frames N --fps F``: a still HDR scene seen through a living eye.

    The frames are rendered by the temporal model's `lax.scan` in chunks of
    `ANIMATION_CHUNK` (one compilation), carrying the dynamics state from chunk to chunk,
    with a progress bar; they go to an MP4 or GIF (tone-mapped with the model's operator)
    or, for an output path without suffix, to a folder of linear EXR frames
    ``frame_00000.exr`` ... Files are written atomically (a folder is filled under a
    temporary name and renamed when complete).
    """
    import shutil
    import uuid

    import equinox as eqx
    import jax.numpy as jnp
    from tqdm import tqdm

    from invglare.commands import options
    from invglare.files.atomic import atomic_path
    from invglare.files.exr import write_exr
    from invglare.models.temporal import frame_luminance_cd_m2
    from invglare.render.temporal_frames import check_display, render_sequence

    if frames is None:
        raise ConfigError("--fps needs --frames (the number of frames to render)")
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
        raise ConfigError(f"--frames must be an integer >= 1, got {frames!r}")
    target = _animation_target(out)
    options.count(frames, "--frames")
    options.positive(fps, "--fps")
    image, scale = _read_scene_and_scale(scene, pixel_scale_deg)
    _check_animation_size(target, out, frames, image)
    model = _load_model(model_path)
    if not model.animated:
        raise ConfigError(
            f"--frames animates a model with dynamics (e.g. model.kind = 'temporal'); "
            f"{model_path} builds a static {type(model).__name__}"
        )
    if fps is not None:
        model = model.with_fps(fps)
    if image.ndim == 3 and not model.is_spectral:
        from invglare._core.colour import rec709_luminance_np

        image = rec709_luminance_np(image)
    output = "linear" if target == "exr" else "display"
    if output == "display":
        check_display(model)  # an unknown tone map fails before any frame is computed
    chunk = min(ANIMATION_CHUNK, frames)
    run = eqx.filter_jit(
        lambda m, im, st: render_sequence(m, im, chunk, st, image_scale_deg=scale, output=output)
    )
    image = jnp.asarray(image)
    # Start adapted to the scene; a concrete state (not None) keeps one compilation for all chunks.
    state = model.init_state(frame_luminance_cd_m2(image, model.luminance_scale))
    config = model.to_config()

    def frames_out():
        nonlocal state
        done = 0
        with tqdm(total=frames, desc="frames", unit="frame", disable=None) as bar:
            while done < frames:
                state, block = run(model, image, state)
                # The last chunk is computed whole (no second compilation); extras are dropped.
                block = np.asarray(block)[: frames - done]
                yield from block
                done += len(block)
                bar.update(len(block))

    if target == "exr":
        staging = out.parent / f".{out.name}.{uuid.uuid4().hex[:12]}.tmp"
        staging.mkdir(parents=True)
        try:
            for i, frame in enumerate(frames_out()):
                write_exr(
                    staging / f"frame_{i:05d}.exr",
                    frame,
                    pixel_scale_deg=scale,
                    config=config,
                    attrs={"frame": i, "fps": model.fps, "scene": str(scene)},
                )
            if out.exists():
                out.rmdir()  # empty, checked above
            staging.rename(out)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
    else:
        with atomic_path(out) as tmp:
            writer = _frame_writer(target, tmp, model.fps)
            try:
                for frame in frames_out():
                    rgb = frame if frame.ndim == 3 else np.repeat(frame[..., None], 3, axis=-1)
                    writer.append_data(np.round(np.clip(rgb, 0.0, 1.0) * 255.0).astype(np.uint8))
            finally:
                writer.close()
    log.info("wrote %s (%d frames at %g frames/s, %s)", out, frames, model.fps, target)


def run_scene_render(
    scene: Path,
    model_path: Path,
    out: Path,
    tonemap_name: str,
    exposure: float,
    iterations: int | None,
    depth: Path | None,
    seed: int,
    model=None,
) -> None:
    """``invglare render`` of a model that renders whole scenes (the holographic eye).

    The frame and its depth (a ``Z`` channel of the scene, `depth`, or none: the model's
    constant depth) are handed to the model as a whole; `iterations` random-phase draws
    are averaged, with a progress bar. An EXR stays linear at the model's pixel scale; a
    PNG is tone-mapped (Reinhard by default).
    """
    import jax

    from invglare.commands import options
    from invglare.files.depth_frames import read_frame_and_depth

    out = output_file(out, "--out", OUTPUT_SUFFIXES)
    options.count(iterations, "--iterations")
    model = _load_model(model_path) if model is None else model
    if not model.renders_scenes:
        raise ConfigError(
            f"--iterations and --depth are for models that render whole scenes (e.g. "
            f"model.kind = 'holographic'); {model_path} builds a {type(model).__name__}"
        )
    loaded = read_frame_and_depth(scene, depth)
    scale = float(model.pixel_scale_deg)
    step = getattr(model, "input_step", 1)
    if loaded.pixel_scale_deg is not None and not np.isclose(
        loaded.pixel_scale_deg, scale * step, rtol=1e-3
    ):
        # The eye's grid fixes the angle of a source pixel: the scene is read at that scale.
        log.warning(
            "%s says %.4g deg/px; %s places its pixels %.4g deg apart (its grid's scale)",
            scene,
            loaded.pixel_scale_deg,
            model_path,
            scale * step,
        )
    log.info(
        "rendering %s through %s (depth: %s)", scene, type(model).__name__, loaded.depth_source
    )
    result = model.render_scene(
        loaded.frame, loaded.depth, jax.random.key(seed), iterations=iterations, progress=True
    )
    params = _tonemap_params(out, tonemap_name, exposure)
    _write(out, np.asarray(result), scale, model, "scene", scene, tonemap_name, params)
