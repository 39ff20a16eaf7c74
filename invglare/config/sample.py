"""The ``[sample]`` table of a fit config: the defaults of ``invglare sample``.

Command-line options win over the table; the table wins over :data:`SAMPLE_DEFAULTS`.

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

**Example:** ``read_sample_section(Path("fits/eye_daylight.toml"))["walkers"]`` is 32.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from invglare.config.section import Section
from invglare.errors import ConfigError
from invglare.files.toml import load_toml

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
    from invglare.config.fit import is_reference_fit
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
