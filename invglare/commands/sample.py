"""``invglare sample``: the emcee posterior of a fit, checkpointed, with its report.

Reads the fit config through :func:`invglare.config.fit.load_fit`, starts from
the stored fit result ``reports/NAME/params.json`` (running the fit first when
there is none), samples with :func:`invglare.fit.sample.sample` into
``reports/NAME/posterior/chain.h5`` and writes the report of
:mod:`invglare.fit.posterior_report` next to it.

An optional ``[sample]`` table of the fit config sets the defaults (command-line
options win):

```toml
[sample]
walkers = 32                  # even, >= 2 x free parameters
steps = 5000                  # step limit (stored steps included)
moves = "stretch"             # or {de = 0.8, de_snooker = 0.2}
batch_size = "auto"           # walkers per compiled evaluation, or an integer
init_scale = 0.1              # starting ball, in fit standard errors
tau_factor = 50.0             # stop when the chain is longer than this many tau
check_every = 100             # steps between convergence checks
likelihood = "pixels"         # or "views" (the fit's residuals)
seed = 0
predictive_draws = 64         # posterior-predictive draws in the report
```

**Example:**

```bash
invglare sample fits/eye_daylight.toml                  # -> reports/eye_daylight/posterior/
invglare sample fits/eye_daylight.toml --resume --steps 20000
```
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

from invglare.errors import ConfigError, InputDataError

log = logging.getLogger("invglare")

#: Keys of the ``[sample]`` table, with their defaults.
SAMPLE_DEFAULTS: dict[str, Any] = {
    "walkers": None,
    "steps": 5000,
    "moves": "stretch",
    "batch_size": "auto",
    "init_scale": 0.1,
    "tau_factor": 50.0,
    "check_every": 100,
    "likelihood": "pixels",
    "seed": 0,
    "predictive_draws": 64,
}


def read_sample_section(config_path: Path) -> dict[str, Any]:
    """The ``[sample]`` table of a fit config, checked, with defaults filled in."""
    from invglare.cie_study.config import is_reference_fit
    from invglare.config.section import Section
    from invglare.files.toml import load_toml
    from invglare.fit.sample import LIKELIHOODS, parse_moves

    config = load_toml(config_path)
    if is_reference_fit(config):
        # No photo and no noise model: there is no posterior to sample.
        raise ConfigError(
            f"{config_path} fits the eye to a reference glare function ([reference]); its "
            "residuals are the model's misfit to a population average, not photon and read "
            "noise, so there is no likelihood to sample; invglare sample takes a photo fit "
            "(a [target] photo with an [observation] noise model)"
        )
    sec = Section(config.get("sample", {}), "sample")
    out = {
        "walkers": sec.get("walkers", int, None),
        "steps": sec.get("steps", int, SAMPLE_DEFAULTS["steps"]),
        "moves": sec.get("moves", (str, dict, list), SAMPLE_DEFAULTS["moves"]),
        "batch_size": sec.get("batch_size", (int, str), SAMPLE_DEFAULTS["batch_size"]),
        "init_scale": sec.get("init_scale", float, SAMPLE_DEFAULTS["init_scale"]),
        "tau_factor": sec.get("tau_factor", float, SAMPLE_DEFAULTS["tau_factor"]),
        "check_every": sec.get("check_every", int, SAMPLE_DEFAULTS["check_every"]),
        "likelihood": sec.choice("likelihood", LIKELIHOODS, SAMPLE_DEFAULTS["likelihood"]),
        "seed": sec.get("seed", int, SAMPLE_DEFAULTS["seed"]),
        "predictive_draws": sec.get("predictive_draws", int, SAMPLE_DEFAULTS["predictive_draws"]),
    }
    sec.finish()
    parse_moves(out["moves"])  # a bad move fails here, before the model is built
    if isinstance(out["batch_size"], str) and out["batch_size"] != "auto":
        raise ConfigError(
            f"sample.batch_size must be an integer or 'auto', got {out['batch_size']!r}"
        )
    for key in ("steps", "check_every", "predictive_draws"):
        if out[key] < 1:
            raise ConfigError(f"sample.{key} must be >= 1, got {out[key]}")
    return out


def _best_choice(params_path: Path) -> dict[str, int]:
    """The discrete choice the stored fit chose (lowest finite loss, as ``invglare fit`` does)."""
    data = json.loads(params_path.read_text(encoding="utf-8"))
    table = data.get("discrete") or []
    rows = [r for r in table if isinstance(r, dict) and "choice" in r]
    if not rows:
        return {}
    finite = [r for r in rows if r.get("loss") is not None and math.isfinite(r["loss"])]
    best = min(finite or rows, key=lambda r: r.get("loss") or math.inf)
    return {str(k): int(v) for k, v in best["choice"].items()}


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

    **Returns:** the posterior folder (``reports/NAME/posterior``).
    """
    import jax

    from invglare.config.fit import load_fit
    from invglare.fit import FitResult
    from invglare.fit.posterior_report import write_posterior_report
    from invglare.fit.sample import sample

    opts = read_sample_section(Path(config))
    if steps is not None:
        opts["steps"] = int(steps)
    if walkers is not None:
        opts["walkers"] = int(walkers)
    if moves is not None:
        opts["moves"] = moves
    if batch_size is not None:
        if batch_size != "auto" and not batch_size.isdigit():
            raise ConfigError(f"--batch-size must be an integer or 'auto', got {batch_size!r}")
        opts["batch_size"] = batch_size if batch_size == "auto" else int(batch_size)

    with jax.enable_x64(True):
        setup = load_fit(config, out_dir=out_dir)
        params_path = setup.out_dir / "params.json"
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
        choice = _best_choice(params_path)
        forward = setup.forward_for(choice)
        folder = setup.out_dir / "posterior"
        chain = folder / "chain.h5"
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
