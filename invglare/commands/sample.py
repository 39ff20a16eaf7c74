"""``invglare sample``: the emcee posterior of a fit, checkpointed, with its report.

Reads the fit config through :func:`invglare.config.fit.load_fit`, starts from
the stored fit result ``params.json``: in the report folder (``runs/NAME`` by default),
else in the config's own folder, else in the committed ``reports/NAME`` (running the fit
first when there is none), samples with :func:`invglare.fit.sample.sample` into
``posterior/chain.h5`` of the report folder and writes the report of
:mod:`invglare.fit.posterior_report` next to it.

An optional ``[sample]`` table of the fit config sets the defaults (command-line
options win; the table is read by :func:`invglare.config.sample.read_sample_section`).

**Example:**

```bash
invglare sample fits/eye_daylight.toml                  # -> runs/eye_daylight/posterior/
invglare sample fits/eye_daylight.toml --resume --steps 20000
invglare sample fits/eye_daylight.toml --out-dir reports/eye_daylight --resume  # the committed
```
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

from invglare.errors import ConfigError, InputDataError

log = logging.getLogger("invglare")


def _stored_choice(params_path: Path) -> dict[str, int]:
    """The discrete choice the stored fit chose: ``params.json``'s ``"discrete"`` table,
    ``{path (or an older model-config key): {"value": chosen, ...}}``."""
    data = json.loads(params_path.read_text(encoding="utf-8"))
    table = data.get("discrete") or {}
    return {
        str(k): int(v["value"]) for k, v in table.items() if isinstance(v, dict) and "value" in v
    }


def run_sample(
    config: Path,
    *,
    resume: bool = False,
    restart: bool = False,
    steps: int | None = None,
    walkers: int | None = None,
    force: bool = False,
    moves: str | None = None,
    batch_size: str | None = None,
    out_dir: Path | None = None,
    progress: bool = True,
) -> Path:
    """Sample the posterior of the fit `config` describes and write its report.

    **Returns:** the posterior folder (``runs/NAME/posterior`` by default).
    """
    from invglare.commands import options
    from invglare.commands.fit import logged_deprecations, precheck_fit_config
    from invglare.config.fit import load_fit
    from invglare.config.sample import read_sample_section
    from invglare.files.atomic import folder_lock
    from invglare.files.outputs import output_folder

    if resume and restart:
        raise ConfigError(
            "--resume and --restart exclude each other: continue the chain or replace it"
        )
    options.count(steps, "--steps")
    options.count(walkers, "--walkers", 2)
    if moves is not None:
        from invglare.fit.sample import parse_moves

        with options.named("--moves"):
            parse_moves(moves)
    if batch_size is not None and batch_size != "auto" and not (
        batch_size.isdigit() and int(batch_size) >= 1
    ):
        raise ConfigError(f"--batch-size must be an integer >= 1 or 'auto', got {batch_size!r}")
    if out_dir is not None:
        output_folder(out_dir, "--out-dir", replaced=True)
    precheck_fit_config(Path(config))
    opts = read_sample_section(Path(config))
    import jax

    if steps is not None:
        opts["steps"] = int(steps)
    if walkers is not None:
        opts["walkers"] = int(walkers)
    if moves is not None:
        opts["moves"] = moves
    if batch_size is not None:
        opts["batch_size"] = batch_size if batch_size == "auto" else int(batch_size)

    with jax.enable_x64(True):
        with logged_deprecations(Path(config)):
            setup = load_fit(config, out_dir=out_dir)
    option = "--out-dir" if out_dir is not None else "fit.out_dir"
    chain = _check_outputs(setup, option, resume)
    _check_walkers_and_steps(opts, setup.space.size, walkers, steps)
    # One run per report folder: a fit or another sample of it waits for this one.
    with folder_lock(setup.out_dir, option=option), jax.enable_x64(True):
        return _sample_and_report(
            setup, chain, config, opts, resume=resume, restart=restart, force=force,
            out_dir=out_dir, progress=progress,
        )  # fmt: skip


def _check_outputs(setup, option: str, resume: bool) -> Path:
    """The report folder, the posterior folder and the chain file, checked before any work."""
    from invglare.files.outputs import output_file, output_folder

    output_folder(setup.out_dir, option, replaced=True)
    folder = setup.out_dir / "posterior"
    output_folder(folder, "the posterior folder")
    chain = output_file(folder / "chain.h5", "the chain file", (".h5",))
    if resume and not chain.is_file():
        raise InputDataError(
            f"there is no chain to resume at {chain}; run without --resume to start one"
        )
    return chain


def _check_walkers_and_steps(opts: dict, n_params: int, walkers, steps) -> None:
    """Walkers even and >= 2 per parameter; the chain (read back whole for its
    diagnostics) within memory."""
    from invglare._core.memory import check_memory

    w_key = "--walkers" if walkers is not None else "sample.walkers"
    n_walkers = opts["walkers"]
    if n_walkers is not None and (n_walkers % 2 or n_walkers < 2 * n_params):
        raise ConfigError(
            f"{w_key} must be even and >= 2 x {n_params} free parameters = {2 * n_params}, "
            f"got {n_walkers}"
        )
    n_walkers = n_walkers or max(32, 4 * n_params)
    s_key = "--steps" if steps is not None else "sample.steps"
    check_memory(
        3 * 8.0 * opts["steps"] * n_walkers * (2 * n_params + 1),
        f"a chain of {opts['steps']} steps x {n_walkers} walkers x {n_params} parameters "
        f"({s_key} {opts['steps']}, {w_key} {n_walkers})",
    )


def _sample_and_report(
    setup, chain: Path, config: Path, opts: dict, *, resume: bool, restart: bool, force: bool,
    out_dir: Path | None, progress: bool,
) -> Path:
    """Sample (running the fit first if there is none) and write the posterior report."""
    from invglare.config.fit import stored_fit
    from invglare.fit import FitResult
    from invglare.fit.posterior_report import write_posterior_report
    from invglare.fit.sample import sample

    params_path = stored_fit(setup)
    if not params_path.is_file():
        from invglare.commands.fit import run_fit

        log.info("no fit result at %s: running the fit first", params_path)
        run_fit(Path(config), out_dir=out_dir, progress=progress)
    fit_result = FitResult.from_json(params_path)
    if list(fit_result.paths) != list(setup.space.paths):
        raise InputDataError(
            f"{params_path} is a fit of {fit_result.paths} but {config} frees "
            f"{list(setup.space.paths)}: the config changed since the fit; run invglare "
            f"fit {config} again"
        )
    forward = setup.forward_for(setup.choice(_stored_choice(params_path)))
    folder = chain.parent
    log.info(
        "sampling %s: %d free parameters, chain %s%s",
        setup.name,
        setup.space.size,
        chain,
        " (resumed)" if resume else "",
    )
    try:
        post = sample(
            setup.space,
            forward,
            setup.target,
            fit_result,
            chain,
            n_walkers=opts["walkers"],
            max_steps=opts["steps"],
            moves=opts["moves"],
            resume=resume,
            restart=restart,
            force=force,
            tau_factor=opts["tau_factor"],
            check_every=opts["check_every"],
            batch_size=opts["batch_size"],
            init_scale=opts["init_scale"],
            seed=opts["seed"],
            likelihood=opts["likelihood"],
            views=setup.views,
            view_options=setup.view_options or None,
            progress=progress,
        )
    except KeyboardInterrupt:
        if chain.is_file():
            log.error(
                "interrupted; every completed step is kept in %s; continue with "
                "invglare sample %s --resume",
                chain,
                config,
            )
        raise
    t = post.timing
    log.info(
        "%d steps x %d walkers, %.1f ms per step (%.2f ms per walker evaluation, "
        "batches of %s)",
        post.n_steps,
        post.n_walkers,
        1e3 * t.get("s_per_step", math.nan),
        1e3 * t.get("s_per_walker_eval", math.nan),
        t.get("batch_size"),
    )
    write_posterior_report(
        post,
        folder,
        space=setup.space,
        forward_template=forward,
        target=setup.target,
        name=setup.name,
        n_predictive=opts["predictive_draws"],
        seed=opts["seed"],
    )
    log.info("%s", post.summary())  # the warnings are its last lines
    log.info("wrote %s (summary.md, summary.json, corner, trace, predictive)", folder)
    return folder
