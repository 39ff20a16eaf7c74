"""The benchmark of a fit of an eye the model did not draw: `fit_unknown_draw`.

A real eye has no seed. The case makes a daylight-eye photo whose lashes and cornea
cells were drawn with another seed than the model config's (``examples/eye_daylight.toml``,
seed 7), on a 128² grid, with truths away from the config's values, and fits it with the
bundled config's settings (``fits/eye_daylight.toml``: its free parameters, stages,
statistics views with their simulated eyes), as ``invglare fit`` would: a temporary synth
spec, photo, model config and fit config are written and read back. It records the wall
time of the whole fit (compilation included), the fitted values with their standard
errors against the truth, and the load.
"""

from __future__ import annotations

import datetime as dt
import re
import tempfile
import time
from pathlib import Path
from typing import Any

from invglare.bench.timing import load_1m
from invglare.errors import ConfigError

#: The case's name (run once, like the fit benchmarks).
UNKNOWN_DRAW_CASES = ("fit_unknown_draw",)

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "fits" / "eye_daylight.toml"
MODEL = ROOT / "examples" / "eye_daylight.toml"
NPIX = 128
#: The photo's eye: another seed than the model config's 7, and truths off its values.
EYE_SEED = 1001
TRUTH = {
    "model.aperture.pupil.diameter_mm": 3.3,
    "model.aperture.upper_lashes.count": 34.0,
    "model.aperture.upper_lashes.mean_angle_deg": -4.0,
}
OBSERVATION = {
    "flux": 3e7, "background": 20.0, "dx_px": -0.18, "dy_px": 0.27, "gain": 2.0,
    "read_noise": 3.0, "saturation": 60000.0,
}  # fmt: skip


def _replace(text: str, pattern: str, repl: str) -> str:
    out, n = re.subn(pattern, repl, text, count=1, flags=re.MULTILINE)
    if n != 1:
        raise ConfigError(f"the unknown-draw benchmark found no {pattern!r} to replace")
    return out


def _write_inputs(folder: Path) -> Path:
    """The photo (by ``invglare synth``'s code), its model config and the fit config: the
    bundled configs' text with the photo, the grid and the eye's seed replaced."""
    from invglare.config.synth import load_synth
    from invglare.config.synth_photo import synthesize, write_synth
    from invglare.files.atomic import write_text_atomic

    model = _replace(MODEL.read_text(), r"^npix = \d+", f"npix = {NPIX}")
    write_text_atomic(folder / "model.toml", model)
    photo_model = _replace(model, r"^seed = \d+", f"seed = {EYE_SEED}")
    write_text_atomic(folder / "photo_model.toml", photo_model)
    spec = ["[synth]", 'model = "photo_model.toml"', "seed = 3", 'pixel_type = "float"', "[set]"]
    spec += [f'"{path}" = {value!r}' for path, value in TRUTH.items()]
    spec += ["[observation]"] + [f"{k} = {v!r}" for k, v in OBSERVATION.items()]
    write_text_atomic(folder / "photo.toml", "\n".join(spec) + "\n")
    synth = load_synth(folder / "photo.toml")
    write_synth(synth, *synthesize(synth))
    fit = _replace(CONFIG.read_text(), r"^file = .*$", 'file = "photo.exr"')
    fit = _replace(fit, r"^config = .*$", 'config = "model.toml"')
    write_text_atomic(folder / "fit.toml", f'[fit]\nout_dir = "report"\n\n{fit}')
    return folder / "fit.toml"


def run_unknown_draw_benchmark() -> dict[str, Any]:
    """Fit the photo of an eye the model did not draw; return one JSON-ready record."""
    import jax

    from invglare.config.fit import load_fit

    record: dict[str, Any] = {
        "case": "fit_unknown_draw",
        "kind": "unknown_draw",
        "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "load_1m_start": load_1m(),
        "config": str(CONFIG.relative_to(ROOT)),
        "npix": NPIX,
        "eye_seed": EYE_SEED,
    }
    with tempfile.TemporaryDirectory() as tmp, jax.enable_x64(True):
        config = _write_inputs(Path(tmp))
        t0 = time.perf_counter()
        setup = load_fit(config)
        result = setup.fit()
        record["wall_s"] = time.perf_counter() - t0
    record["timing_s"] = dict(result.timing_s)
    record["converged"] = bool(result.converged)
    record["message"] = result.message
    record["parameters"] = {
        p: {
            "value": result.values[p],
            "stderr": result.stderr[p],
            "truth": (result.truth or {}).get(p),
        }
        for p in result.paths
    }
    record["load_1m_end"] = load_1m()
    return record


def unknown_draw_markdown(record: dict[str, Any]) -> list[str]:
    """The case's section of bench.md."""
    lines = [
        f"## Fit of an eye the model did not draw: {record['case']} ({record['npix']}² photo)",
        "",
        f"Measured {record['date']}: `{record['config']}`'s settings on a {record['npix']}² "
        f"daylight-eye photo drawn with eye seed {record['eye_seed']} (the model's is 7). "
        f"Wall time {record['wall_s']:.0f} s for the whole fit, compilation included "
        f"(compile {record['timing_s'].get('compile', 0):.0f} s, solve "
        f"{record['timing_s'].get('solve', 0):.0f} s). Load (1 min) {record['load_1m_start']} "
        f"at the start, {record['load_1m_end']} at the end. {record['message']}.",
        "",
        "| parameter | value | stderr | truth | (value - truth) / stderr |",
        "|---|---:|---:|---:|---:|",
    ]
    for path, p in record["parameters"].items():
        truth = p["truth"]
        pull = (
            "—"
            if truth is None or not p["stderr"]
            else f"{(p['value'] - truth) / p['stderr']:+.2f}"
        )
        lines.append(
            f"| `{path}` | {p['value']:.5g} | {p['stderr']:.3g} | "
            f"{'—' if truth is None else format(truth, '.5g')} | {pull} |"
        )
    return lines


__all__ = ["UNKNOWN_DRAW_CASES", "run_unknown_draw_benchmark", "unknown_draw_markdown"]
