"""The ``invglare`` command.

Heavy imports (JAX, the models) happen inside the commands so that ``--help`` is
instant. A user mistake (any :class:`~invglare.errors.InvglareError`) is printed as
one line on stderr with exit status 2; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import functools
import logging
import sys
from pathlib import Path
from typing import Annotated

import typer
import typer.core

from invglare._core.allocator import retain_freed_memory
from invglare.errors import InvglareError
from invglare.files.outputs import RUNS_DIR

#: The click (or typer's own copy of click) exception behind every usage error.
_CLICK_ERROR = next(c for c in typer.BadParameter.__mro__ if c.__name__ == "ClickException")


class _OneLineErrors(typer.core.TyperGroup):
    """Usage errors (an option that is not an integer, an unknown option) as one line, like
    every other error of the command, instead of a framed panel."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        if not standalone_mode:
            return super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        try:
            rv = super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        except _CLICK_ERROR as err:
            if type(err).__name__ == "NoArgsIsHelpError":  # bare `invglare`: the help
                err.show()
                sys.exit(err.exit_code)
            ctx = getattr(err, "ctx", None)
            where = f" (see {ctx.command_path} --help)" if ctx is not None else ""
            typer.echo(f"invglare: error: {err.format_message()}{where}", err=True)
            sys.exit(err.exit_code)
        except typer.Abort:
            typer.echo("invglare: aborted", err=True)
            sys.exit(1)
        sys.exit(rv if isinstance(rv, int) else 0)


app = typer.Typer(
    cls=_OneLineErrors,
    name="invglare",
    help="Differentiable glare models: PSFs of eyes and cameras, fitted to photos.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

log = logging.getLogger("invglare")


def _reports_user_errors(command):
    """Turn an InvglareError into one clear line and a non-zero exit."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            return command(*args, **kwargs)
        except InvglareError as err:
            typer.echo(f"invglare: error: {err}", err=True)
            raise typer.Exit(code=2) from None
        except KeyboardInterrupt:
            typer.echo("invglare: interrupted; nothing half-written was left behind", err=True)
            raise typer.Exit(code=130) from None

    return wrapper


def _print_version(value: bool) -> None:
    if value:
        from invglare import __version__

        typer.echo(f"invglare {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    verbose: Annotated[int, typer.Option("--verbose", "-v", count=True, help="More logging.")] = 0,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="Only errors.")] = False,
    version: Annotated[
        bool,
        typer.Option(
            "--version", callback=_print_version, is_eager=True, help="Print the version and exit."
        ),
    ] = False,
) -> None:
    level = logging.ERROR if quiet else (logging.DEBUG if verbose > 1 else logging.INFO)
    logging.basicConfig(level=level, format="%(message)s", stream=sys.stderr)
    # Before any JAX work: XLA's per-call buffers then stay mapped (see invglare._core.allocator).
    retain_freed_memory()
    # JAX reports every accelerator backend it did not find; that is noise on a CPU machine.
    logging.getLogger("jax._src.xla_bridge").setLevel(logging.ERROR)


@app.command()
@_reports_user_errors
def psf(
    config: Annotated[Path, typer.Argument(help="Model config (TOML).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output EXR file.")] = Path("psf.exr"),
    npix: Annotated[int | None, typer.Option(help="Output size in pixels.")] = None,
    pixel_scale_deg: Annotated[
        float | None, typer.Option("--pixel-scale-deg", help="Output pixel scale (deg/px).")
    ] = None,
    wavelengths_nm: Annotated[
        str | None,
        typer.Option(
            "--wavelengths-nm", help="One value (550), a list (450,550,650) or 380:770:32."
        ),
    ] = None,
    half: Annotated[bool, typer.Option(help="Write half-float pixels.")] = False,
    png: Annotated[
        Path | None, typer.Option(help="Also write a log-scaled PNG preview here.")
    ] = None,
) -> None:
    """Compute the PSF of a model and write it as a self-describing OpenEXR file.

    A monochrome PSF is channel Y, a spectral one linear R, G, B; the header holds
    pixelScaleDeg, wavelengthsNm and the full model config.
    """
    from invglare.commands.psf import run_psf

    run_psf(config, out, npix, pixel_scale_deg, wavelengths_nm, half, png)


@app.command()
@_reports_user_errors
def render(
    scene: Annotated[Path, typer.Argument(help="Linear HDR scene (EXR, with pixelScaleDeg).")],
    model: Annotated[Path, typer.Option("--model", "-m", help="Model config (TOML).")],
    out: Annotated[
        Path,
        typer.Option(
            "--out",
            "-o",
            help="Output .exr (linear) or .png; with --frames .mp4, .gif or a folder (EXR frames).",
        ),
    ] = Path("glare.png"),
    mode: Annotated[
        str,
        typer.Option(
            help="convolve (whole frame), billboard (linear PSFs at the bright pixels, then "
            "--tonemap) or kakimoto (Kakimoto et al.'s compositing: each glare tone-mapped by "
            "the sigmoid into a billboard, scaled by its pixel, blended onto the scene under "
            "--tonemap; black stays black)."
        ),
    ] = "convolve",
    threshold: Annotated[
        float | None,
        typer.Option(help="Billboard threshold in the scene's units (default: max / 100)."),
    ] = None,
    max_bright: Annotated[int, typer.Option(help="Most billboards.")] = 256,
    tonemap: Annotated[str, typer.Option(help="PNG tone map: reinhard, kakimoto, gamma, srgb.")] = (
        "reinhard"
    ),
    exposure: Annotated[float, typer.Option(help="Exposure for the gamma / srgb maps.")] = 1.0,
    pixel_scale_deg: Annotated[
        float | None,
        typer.Option("--pixel-scale-deg", help="Scene pixel scale if the EXR lacks one."),
    ] = None,
    frames: Annotated[
        int | None,
        typer.Option(
            help="Animate: render this many frames of a temporal model (model.kind = "
            "'temporal'), tone-mapped with the model's own operator."
        ),
    ] = None,
    fps: Annotated[
        float | None, typer.Option(help="Frame rate of the animation (default: the model's).")
    ] = None,
    iterations: Annotated[
        int | None,
        typer.Option(help="Random-phase draws averaged by a whole-scene model (holographic)."),
    ] = None,
    depth: Annotated[
        Path | None,
        typer.Option(help="Depth buffer (EXR) of the scene for a holographic model."),
    ] = None,
    seed: Annotated[int, typer.Option(help="Seed of a holographic model's phases.")] = 0,
) -> None:
    """Render a model's glare onto an HDR scene: EXR stays linear, PNG is tone-mapped.

    With --frames, a temporal model animates the scene (the eye's pupil, lens, vitreous
    and lids move frame by frame) into an .mp4, a .gif or a folder of linear EXR frames.
    A veiling-glare model (lens ghosts) gives each of the --max-bright brightest pixels
    above --threshold the ghosts of its own direction (--mode does not apply); so does a
    Kakimoto model with masking = 'position' with its glare PSF (--mode billboard). A
    holographic eye (model.kind = 'holographic') renders the whole scene from its pixels
    as point sources, averaging --iterations random-phase draws (--depth: the depth
    buffer; a Z channel of the scene is used when there is one).
    """
    from invglare.commands.render import run_render

    run_render(
        scene,
        model,
        out,
        mode,
        threshold,
        max_bright,
        tonemap,
        exposure,
        pixel_scale_deg,
        frames=frames,
        fps=fps,
        iterations=iterations,
        depth=depth,
        seed=seed,
    )


@app.command()
@_reports_user_errors
def scene(
    name: Annotated[
        str, typer.Argument(help="street_lights_at_night, sunlit_specular_highlight, candle.")
    ],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output EXR.")] = Path("scene.exr"),
    npix: Annotated[int, typer.Option(help="Image size in pixels.")] = 256,
    seed: Annotated[int, typer.Option(help="Random seed of the procedural scene.")] = 0,
    depth: Annotated[
        Path | None,
        typer.Option(help="Also write the scene's depth buffer (EXR, Z in metres) here."),
    ] = None,
) -> None:
    """Write one of the bundled procedural HDR scenes (linear cd/m^2) as EXR."""
    from invglare.commands.render import run_scene

    run_scene(name, out, npix, seed, depth)


@app.command()
@_reports_user_errors
def gallery(
    models: Annotated[
        list[Path] | None,
        typer.Argument(
            help="Eye / camera configs (TOML); default: daylight and night eyes, the daylight "
            "eye without lashes, a 6-blade camera with and without a cross-screen filter."
        ),
    ] = None,
    out_dir: Annotated[
        Path, typer.Option(help="Where gallery.md and gallery/*.png go (the committed: reports).")
    ] = RUNS_DIR,
    scene: Annotated[
        str, typer.Option(help="Bundled scene rendered with each PSF.")
    ] = "street_lights_at_night",
    npix: Annotated[int, typer.Option(help="PSF and scene size in pixels.")] = 256,
    wavelengths_nm: Annotated[
        str,
        typer.Option(
            "--wavelengths-nm",
            help="Spectrum of every model (RGB PSFs); 'config' keeps each config's own.",
        ),
    ] = "400:700:8",
    scene_scale: Annotated[
        str,
        typer.Option(
            help="Scene pixels as a multiple of each PSF's pixel scale (the glare stays "
            "visible), or 'scene' for the scene's own deg/px (0.05: the PSF covers a few pixels)."
        ),
    ] = "2",
) -> None:
    """Show aperture, log PSF and a rendered scene for a few eyes and cameras.

    Writes OUT_DIR/gallery.md and one PNG row per model in OUT_DIR/gallery/.
    """
    from invglare.commands.gallery import run_gallery

    run_gallery(
        models,
        out_dir,
        scene=scene,
        npix=npix,
        wavelengths_nm=None if wavelengths_nm == "config" else wavelengths_nm,
        scene_scale=scene_scale,
    )


@app.command()
@_reports_user_errors
def bench(
    cases: Annotated[
        list[str] | None,
        typer.Argument(help="Run only cases whose names contain these (e.g. psf, eye, fit)."),
    ] = None,
    out_dir: Annotated[
        Path, typer.Option(help="Where bench.md and bench.json go (the committed: reports).")
    ] = RUNS_DIR,
    sizes: Annotated[str, typer.Option(help="Comma-separated N values.")] = "256,512,1024,2048",
    repeats: Annotated[int, typer.Option(help="Timed repetitions per case.")] = 20,
    skip: Annotated[
        list[str] | None,
        typer.Option(
            help="Skip cases whose names contain this; repeatable (--skip fit skips the fit "
            "benchmark). FFT floors always run with the pipelines."
        ),
    ] = None,
    fit_npix: Annotated[int, typer.Option(help="Photo size of the fit benchmark.")] = 128,
    budget_s: Annotated[
        float, typer.Option(help="At most this many seconds of timed repeats per case and N.")
    ] = 20.0,
) -> None:
    """Benchmark the pipelines against the bare FFT floor measured in the same run.

    Also runs the fit benchmark (invglare's fit against scipy's finite-difference least
    squares on the same problem, once, not per size) and the sampling benchmark (emcee
    steps of the daylight-eye posterior, batched and per walker) unless skipped.
    """
    from invglare.bench.runner import run_bench
    from invglare.errors import ConfigError

    try:
        ns = [int(s) for s in sizes.split(",")]
    except ValueError:
        raise ConfigError(f"--sizes must be comma-separated integers, got {sizes!r}") from None
    run_bench(
        cases or [], out_dir, ns, repeats, skip=skip or [], fit_npix=fit_npix, budget_s=budget_s
    )


@app.command()
@_reports_user_errors
def regress(
    cases: Annotated[
        list[str] | None, typer.Argument(help="Cases to run (default: all; --list names them).")
    ] = None,
    update: Annotated[
        bool, typer.Option("--update", help="Rewrite the stored PSFs of the cases that differ.")
    ] = False,
    reason: Annotated[
        str | None,
        typer.Option(help="Why the goldens change (required with --update; logged in CHANGES.md)."),
    ] = None,
    cie: Annotated[
        list[str] | None,
        typer.Option(
            "--cie",
            metavar="AGE,PIGMENT",
            help="Instead of the suite: fit the eye model to the CIE glare spread function "
            "for this age (years) and pigmentation (0-1.2), e.g. 25,0.5; repeatable.",
        ),
    ] = None,
    golden_dir: Annotated[Path, typer.Option(help="Folder of the golden EXRs.")] = Path(
        "tests/golden"
    ),
    out_dir: Annotated[
        Path,
        typer.Option(
            help="Reports go here (regression.md, regression/, cie/; the committed: reports)."
        ),
    ] = RUNS_DIR,
    list_cases: Annotated[bool, typer.Option("--list", help="List the cases and exit.")] = False,
) -> None:
    """Golden regression: recompute reference PSFs of every model and mode and compare them.

    Writes runs/regression.md with metrics per case and difference images; exits 1
    naming the cases outside tolerance. With --cie, fits the eye model's radial profile
    to the CIE disability-glare function instead (runs/cie/).
    """
    if cie:
        from invglare.commands.regress import run_cie

        if cases or update or reason is not None or list_cases:
            from invglare.errors import ConfigError

            raise ConfigError("--cie runs the CIE fits only; drop the case names and --update")
        run_cie(cie, out_dir)
        return
    from invglare.commands.regress import run_regress

    run_regress(cases or [], update, reason, golden_dir, out_dir, list_cases)


@app.command()
@_reports_user_errors
def synth(
    specs: Annotated[
        list[Path], typer.Argument(help="Synth specs (TOML), e.g. data_synthetic/*.toml.")
    ],
    out_dir: Annotated[
        Path | None, typer.Option(help="Write here instead of next to each spec.")
    ] = None,
) -> None:
    """Synthetic target photos with ground truth: NAME.exr (counts) and NAME.truth.json.

    Poisson and read noise from the spec's seed, clipping at the saturation level; the
    same spec and seed give identical files.
    """
    from invglare.commands.synth import run_synth

    run_synth(specs, out_dir)


@app.command()
@_reports_user_errors
def fit(
    config: Annotated[Path, typer.Argument(help="Fit config (TOML), e.g. fits/eye_daylight.toml.")],
    out_dir: Annotated[
        Path | None, typer.Option(help="Report folder (default: fit.out_dir or runs/NAME).")
    ] = None,
    n_starts: Annotated[int | None, typer.Option(help="Override solver.n_starts.")] = None,
    max_steps: Annotated[int | None, typer.Option(help="Override solver.max_steps.")] = None,
    progress: Annotated[
        bool | None,
        typer.Option(help="Show a progress bar (default: when stderr is a terminal)."),
    ] = None,
) -> None:
    """Fit a glare model to a photo; write report.md, params.json and figures.

    The report folder is replaced as a whole once complete: an interrupted fit
    leaves no half-written report.
    """
    from invglare.commands.fit import run_fit

    run_fit(config, out_dir, n_starts, max_steps, progress)


@app.command("fit-batch")
@_reports_user_errors
def fit_batch(
    config: Annotated[Path, typer.Argument(help="Fit config (TOML), e.g. fits/eye_daylight.toml.")],
    photos: Annotated[
        list[str],
        typer.Argument(
            help="Photos: files, folders, quoted globs ('data/*.exr') or a .csv photo table "
            "(columns photo, name, pixel_scale_deg, saturation, channel, linear, truth)."
        ),
    ],
    out_dir: Annotated[
        Path | None,
        typer.Option(
            help="The fit's report folder (default: fit.out_dir or runs/NAME); the batch "
            "goes to its batch/ subfolder."
        ),
    ] = None,
    scheduler: Annotated[
        str | None,
        typer.Option(
            help="Address of a running Dask scheduler (tcp://HOST:PORT); default: a local "
            "cluster, closed at the end."
        ),
    ] = None,
    workers: Annotated[
        int | None,
        typer.Option(
            help="Worker processes of the local cluster (default: cores), each pinned to a "
            "core of its own on Linux."
        ),
    ] = None,
    vmap: Annotated[
        int, typer.Option(help="Fit up to this many same-size photos in one vmapped solve.")
    ] = 1,
    n_starts: Annotated[int | None, typer.Option(help="Override solver.n_starts.")] = None,
    max_steps: Annotated[int | None, typer.Option(help="Override solver.max_steps.")] = None,
    resume: Annotated[
        bool, typer.Option(help="Skip photos whose report exists (--no-resume refits them).")
    ] = True,
    cache_dir: Annotated[
        Path | None,
        typer.Option(
            help="JAX's persistent compilation cache on the workers (default "
            "~/.cache/invglare/jax)."
        ),
    ] = None,
    progress: Annotated[bool, typer.Option(help="Show a progress bar over photos.")] = True,
) -> None:
    """Fit one config to many photos on Dask: runs/NAME/batch/PHOTO/ and a batch table.

    Each photo is a task on a local cluster (one single-threaded worker process per
    core) or on the cluster at --scheduler. A photo that fails is recorded with its
    reason and the others go on; the exit status is 1 when any failed or did not
    converge. A rerun skips the photos that have a report (an interrupted batch resumes).
    """
    from invglare.commands.fit_batch import run_fit_batch

    summary = run_fit_batch(
        config, photos, out_dir=out_dir, scheduler=scheduler, workers=workers, vmap=vmap,
        n_starts=n_starts, max_steps=max_steps, resume=resume, progress=progress,
        cache_dir=cache_dir,
    )  # fmt: skip
    failures = summary.failures
    if failures:
        for row in failures:
            typer.echo(f"FAIL {row.name} ({row.status}): {row.reason}", err=True)
        typer.echo(
            f"invglare fit-batch: {len(failures)} of {len(summary.rows)} photo(s) failed or did "
            f"not converge: {', '.join(r.name for r in failures)} "
            f"(see {summary.folder / 'batch.md'})",
            err=True,
        )
        raise typer.Exit(code=1)


@app.command()
@_reports_user_errors
def sample(
    config: Annotated[Path, typer.Argument(help="Fit config (TOML), e.g. fits/eye_daylight.toml.")],
    resume: Annotated[
        bool, typer.Option("--resume", help="Continue the stored chain (after Ctrl-C or a kill).")
    ] = False,
    restart: Annotated[
        bool, typer.Option("--restart", help="Replace a stored chain instead of continuing it.")
    ] = False,
    steps: Annotated[
        int | None,
        typer.Option(help="Step limit, stored steps included (default: sample.steps, or 5000)."),
    ] = None,
    walkers: Annotated[
        int | None, typer.Option(help="Walkers: even, >= 2 x parameters (default max(32, 4p)).")
    ] = None,
    force: Annotated[
        bool, typer.Option("--force", help="Sample even if the fit did not converge.")
    ] = False,
    moves: Annotated[
        str | None, typer.Option(help="emcee move: stretch, de, de_snooker, kde or walk.")
    ] = None,
    batch_size: Annotated[
        str | None, typer.Option(help="Walkers per compiled evaluation, or 'auto' (timed).")
    ] = None,
    out_dir: Annotated[
        Path | None, typer.Option(help="Report folder of the fit (default: runs/NAME).")
    ] = None,
    progress: Annotated[bool, typer.Option(help="Show a progress bar.")] = True,
) -> None:
    """Sample the posterior of a fit with emcee; write runs/NAME/posterior/.

    Starts around the stored fit (params.json in the report folder, else the committed
    reports/NAME/; the fit runs first if there is none), checkpoints every step to
    posterior/chain.h5, stops once the chain is longer than 50 autocorrelation times or
    at the step limit, and writes summary.md / summary.json, corner, trace and
    posterior-predictive plots.
    """
    from invglare.commands.sample import run_sample

    run_sample(
        config,
        resume=resume,
        restart=restart,
        steps=steps,
        walkers=walkers,
        force=force,
        moves=moves,
        batch_size=batch_size,
        out_dir=out_dir,
        progress=progress,
    )


@app.command("export-kernel")
@_reports_user_errors
def export_kernel(
    config: Annotated[Path, typer.Argument(help="Model config (TOML), shift invariant.")],
    target: Annotated[
        str, typer.Option("--for", help="The renderer: blender (compositor) or unreal (bloom).")
    ],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output EXR file.")] = Path("kernel.exr"),
    npix: Annotated[
        int | None, typer.Option(help="Kernel size in pixels, odd (default: the PSF's field).")
    ] = None,
    pixel_scale_deg: Annotated[
        float | None,
        typer.Option("--pixel-scale-deg", help="The frame's pixel scale (default: the model's)."),
    ] = None,
    wavelengths_nm: Annotated[
        str | None,
        typer.Option("--wavelengths-nm", help="One value, a list or 380:770:32 (RGB kernel)."),
    ] = None,
    viewport: Annotated[
        str | None, typer.Option(help="Screen size WIDTHxHEIGHT (sets Unreal's Convolution Scale).")
    ] = None,
    fov_deg: Annotated[
        float | None,
        typer.Option("--fov-deg", help="Horizontal field of view; with --viewport, the scale."),
    ] = None,
) -> None:
    """Write a model's PSF as a renderer's convolution kernel: odd size, linear float EXR.

    --for blender: for the compositor's Glare (Kernel) and Convolve nodes (stored rotated
    by 180 deg, as Blender gathers). --for unreal: for the convolution bloom (peak at UV
    0.5, 0.5, unclipped). The command prints how to set the renderer up, including what
    its kernel normalisation does to a coloured kernel.
    """
    from invglare.commands.export_kernel import run_export_kernel

    run_export_kernel(
        config,
        out,
        target,
        npix,
        pixel_scale_deg,
        wavelengths_nm,
        viewport=viewport,
        fov_deg=fov_deg,
    )


def main() -> None:
    app()


if __name__ == "__main__":
    main()
