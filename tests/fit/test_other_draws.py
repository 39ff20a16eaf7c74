"""Recovery of eyes the model did not draw: the bundled fit configs
``fits/eye_daylight_other_draws.toml`` and ``fits/eye_night_other_draws.toml`` (statistics
weighed by the scatter between simulated eyes) rerun on photos of eyes drawn with other
seeds than the model config's (``invglare synth`` of ``data_synthetic/eye_*_other_draws.toml``:
truths spread over the bounds, each photo with its own noise), as ``invglare fit-batch``
fits them, and the committed batch reports of all eight eyes checked. The daylight config
is refitted here in full; the night config is checked through its committed batch only
(its refit, the same statistics machinery on a night eye, kept one of CI's two cores busy
for ten minutes, and the suite has to stay inside CI's hour).

What these fits recover (README, "Eyes the model did not draw"): the pupil, the grating
spacing and the source; the daylight eye's lash count and mean angle only loosely, and not
always within their local standard errors (an eye's own lashes can read as a lash or two
more than it has, and the first stage can land on another minimum in count and angle).
What every report must then do is say so: each parameter whose known truth lies beyond 3
standard errors carries a ``truth_beyond_3se`` flag.
"""

from __future__ import annotations

import copy
import csv
import dataclasses
import math
from pathlib import Path

import helpers
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from typer.testing import CliRunner

from invglare.cli import app
from invglare.config.batch import PhotoJob, photo_config
from invglare.config.fit import load_fit
from invglare.config.synth import load_synth_specs
from invglare.config.synth_photo import build_truth_forward
from invglare.files.toml import load_toml
from invglare.fit import fit
from invglare.fit.draw_scatter import scatter_options
from invglare.fit.result import FitResult
from invglare.fit.views import make_residual_fn

ROOT = Path(__file__).resolve().parents[2]
PUPIL = "model.aperture.pupil.diameter_mm"
COUNT = "model.aperture.upper_lashes.count"
SPACING = "model.aperture.gratings.spacing_mm"
SOURCE = ("obs.flux", "obs.background", "obs.dx_px", "obs.dy_px")


def _population(name: str) -> list[dict[str, str]]:
    with open(ROOT / "data_synthetic" / name / "population.csv", newline="") as f:
        return list(csv.DictReader(f))


def _setup(name: str, photo: str):
    """The bundled fit config `name` pointed at one of its photos (call under x64)."""
    config = ROOT / "fits" / f"{name}.toml"
    job = PhotoJob(photo.removesuffix(".exr"), ROOT / "data_synthetic" / name / photo)
    return load_fit(config, config=photo_config(load_toml(config), job))


def _check_flags_tell(paths, values, stderr, truth, flags) -> dict[str, float]:
    """Each truth beyond 3 standard errors is flagged, and no other; returns the pulls."""
    pulls = {p: (values[p] - truth[p]) / stderr[p] for p in paths}
    assert all(math.isfinite(z) for z in pulls.values()), pulls
    flagged = {f["path"] for f in flags if f["kind"] == "truth_beyond_3se"}
    assert flagged == {p for p, z in pulls.items() if abs(z) > 3.0}, (flagged, pulls)
    assert not any(f["kind"] == "not_at_optimum" for f in flags), flags
    return pulls


@pytest.mark.slow
def test_a_daylight_eye_the_model_did_not_draw(tmp_path) -> None:
    """The README's ``invglare fit fits/eye_daylight_other_draws.toml`` in full (its target
    is the first of the five bundled eyes): pupil within 2 % and 3 standard errors, lash
    count within 2, the source's flux, background and centre within 3 standard errors, and
    every miss flagged, in the report's params.json."""
    row = _population("eye_daylight_other_draws")[0]
    config = ROOT / "fits" / "eye_daylight_other_draws.toml"
    assert load_toml(config)["target"]["file"].endswith(f"/{row['photo']}")
    out = tmp_path / "fit"
    done = CliRunner().invoke(app, ["fit", str(config), "--out-dir", str(out), "--no-progress"])
    assert done.exit_code == 0, done.output
    result = FitResult.from_json(out / "params.json")
    v, t = result.values, result.truth
    pulls = _check_flags_tell(result.paths, v, result.stderr, t, result.flags)
    assert abs(v[PUPIL] / t[PUPIL] - 1.0) < 0.02, (v[PUPIL], t[PUPIL])
    assert abs(v[COUNT] - t[COUNT]) < 2.0, (v[COUNT], t[COUNT])
    assert all(abs(pulls[p]) < 3.0 for p in (PUPIL, *SOURCE)), pulls
    assert "simulated eyes" in result.message


@pytest.mark.slow
def test_eyes_drawn_anew_at_one_truth_give_lash_counts_within_a_lash_or_two() -> None:
    """What the statistics recover from eyes the model did not draw, apart from where a fit
    starts: four daylight eyes drawn as ``invglare synth`` draws them (other eye seeds,
    other noise) at the truth of the third bundled eye, each fitted from that truth with the
    scatter between eyes measured there, as the final stage of the bundled config does.
    Their lash counts scatter about the truth by about a lash (README, "Eyes the model did
    not draw"), their pupils by about 1 % (one of the four is 2.3 % small)."""
    name = "eye_daylight_other_draws"
    spec = load_synth_specs(ROOT / "data_synthetic" / f"{name}.toml")[2]
    counts, pupils = [], []
    with helpers.x64():
        setup = _setup(name, _population(name)[2]["photo"])
        space, template, views = setup.space, setup.forward, setup.views
        truth = np.asarray([setup.truth[p] for p in space.paths])
        latent = space.to_latent(jnp.asarray(truth))
        first = make_residual_fn(space, template, setup.target, views,
                                 view_options=setup.view_options)  # fmt: skip
        options = scatter_options(first, latent, setup.view_options)
        for k in range(4):
            model_config = copy.deepcopy(spec.model_config)
            model_config["model"]["eye"]["seed"] = 7000 + k
            eye = build_truth_forward(dataclasses.replace(spec, model_config=model_config))
            photo = eye.obs.sample(jax.random.key(900 + k), eye.model())
            result = fit(space, template, np.asarray(photo, np.float64), views,
                         starts=truth[None], n_starts=1, view_options=options, max_steps=60,
                         batch="loop", diagnostics=False, final_likelihood=False)  # fmt: skip
            counts.append(result.values[COUNT])
            pupils.append(result.values[PUPIL])
    t = setup.truth
    assert all(abs(c - t[COUNT]) < 2.0 for c in counts), (counts, t[COUNT])
    assert abs(np.mean(counts) - t[COUNT]) < 1.0, (counts, t[COUNT])
    assert all(abs(d / t[PUPIL] - 1.0) < 0.03 for d in pupils), (pupils, t[PUPIL])


def test_the_bundled_photos_were_drawn_with_other_seeds_than_the_models() -> None:
    """What makes the tests here honest: no photo shares the fit model's random draw, and
    no pixel is fitted."""
    for name, model in (("eye_daylight_other_draws", "eye_daylight"),
                        ("eye_night_other_draws", "eye_night")):  # fmt: skip
        seed = load_toml(ROOT / "examples" / f"{model}.toml")["model"]["eye"]["seed"]
        seeds = [int(r["model.eye.seed"]) for r in _population(name)]
        assert seed not in seeds and len(set(seeds)) == len(seeds), (seed, seeds)
        fit = load_toml(ROOT / "fits" / f"{name}.toml")
        assert "pixels" not in fit["views"], fit["views"]
        assert all(o.get("draws", 0) >= 16 for o in fit["view_options"].values())


def _committed(name: str):
    for row in _population(name):
        report = ROOT / "reports" / name / "batch" / row["photo"].removesuffix(".exr")
        r = FitResult.from_json(report / "params.json")
        pulls = _check_flags_tell(r.paths, r.values, r.stderr, r.truth, r.flags)
        yield row["photo"], r.values, r.truth, pulls


def test_the_committed_daylight_batch_recovers_pupil_and_source_and_flags_the_rest() -> None:
    """All five committed daylight eyes: pupil within 2 % and 3 standard errors, the
    source covered, and each report's flags naming exactly the parameters whose truth is
    beyond 3 standard errors."""
    for photo, values, truth, pulls in _committed("eye_daylight_other_draws"):
        assert abs(values[PUPIL] / truth[PUPIL] - 1.0) < 0.02, (photo, values[PUPIL])
        assert all(abs(pulls[p]) < 3.0 for p in (PUPIL, *SOURCE)), (photo, pulls)


def test_the_committed_night_batch_recovers_pupil_and_spacing_and_flags_the_rest() -> None:
    """All three committed night eyes: pupil within 2 %, grating spacing within 3 % and 3
    standard errors, and the flags naming exactly the truths beyond 3 standard errors."""
    for photo, values, truth, pulls in _committed("eye_night_other_draws"):
        assert abs(values[PUPIL] / truth[PUPIL] - 1.0) < 0.02, (photo, values[PUPIL])
        assert abs(values[SPACING] / truth[SPACING] - 1.0) < 0.03, (photo, values[SPACING])
        assert abs(pulls[SPACING]) < 3.0, (photo, pulls)
