"""`invglare sample` end to end: it runs the missing fit, samples, refuses to overwrite, resumes."""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import jax
import numpy as np
import pytest
from test_sample import TRUE_D, TRUE_FLUX

from invglare.aperture import Aperture, Disk
from invglare.fit import Observation
from invglare.fit.sample import load_chain
from invglare.models.aperture_psf import AperturePSF


@pytest.mark.slow
def test_sample_command_fits_samples_resumes_and_reports(tmp_path):
    """`invglare sample` on a 64-px disk photo: runs the missing fit, samples, resumes."""
    from typer.testing import CliRunner

    from invglare.cli import app
    from invglare.files.exr import write_exr

    # The plain AperturePSF (unit energy) of the model config, not CollectingPupil.
    inner = AperturePSF.build(
        Aperture((Disk(TRUE_D),)), focal_length_mm=17.0, npix=64, pixel_scale_deg=0.0035,
        aperture_npix=64, window_mm=5.4,
    )  # fmt: skip
    obs = Observation(flux=TRUE_FLUX, background=20.0, gain=2.0, read_noise=3.0)
    photo = np.asarray(obs.sample(jax.random.key(3), inner()))
    write_exr(tmp_path / "photo.exr", photo.astype(np.float32), pixel_scale_deg=0.0035)
    (tmp_path / "model.toml").write_text(textwrap.dedent("""
        [model]
        kind = "aperture"
        focal_length_mm = 17.0
        aperture_npix = 64
        window_mm = 5.4
        [[model.shapes]]
        kind = "disk"
        diameter_mm = 3.3
        [spectrum]
        wavelengths_nm = 550
        """))  # fmt: skip
    (tmp_path / "disk.toml").write_text(textwrap.dedent(f"""
        [fit]
        out_dir = {str(tmp_path / "out")!r}
        [target]
        file = "photo.exr"
        [model]
        config = "model.toml"
        [observation]
        gain = 2.0
        read_noise = 3.0
        [[free]]
        path = "model.aperture.shapes[0].diameter_mm"
        lower = 2.0
        upper = 5.0
        init = 3.3
        [[free]]
        path = "obs.flux"
        lower = 0.0
        upper = inf
        [solver]
        n_starts = 1
        covariance_scale = "absolute"
        [sample]
        predictive_draws = 8
        check_every = 20
        """))  # fmt: skip
    runner = CliRunner()
    args = ["sample", str(tmp_path / "disk.toml"), "--walkers", "8", "--batch-size", "8",
            "--no-progress"]  # fmt: skip
    r = runner.invoke(app, [*args, "--steps", "60"])
    assert r.exit_code == 0, r.output
    post_dir = tmp_path / "out" / "posterior"
    assert (tmp_path / "out" / "params.json").is_file()  # the fit ran first
    for f in ("chain.h5", "summary.md", "summary.json", "corner.png", "trace.png",
              "predictive.png"):  # fmt: skip
        assert (post_dir / f).is_file(), f
    assert load_chain(post_dir / "chain.h5").n_steps == 60
    r = runner.invoke(app, [*args, "--steps", "80"])
    assert r.exit_code == 2 and "--resume" in r.output
    r = runner.invoke(app, [*args, "--steps", "80", "--resume"])
    assert r.exit_code == 0, r.output
    summary = json.loads((post_dir / "summary.json").read_text())
    assert summary["n_steps"] == 80 and [x["start_step"] for x in summary["runs"]] == [0, 60]
    # A posterior elsewhere (--out-dir) starts from the stored fit: no second fit runs there.
    elsewhere = tmp_path / "elsewhere"
    r = runner.invoke(app, [*args, "--steps", "20", "--out-dir", str(elsewhere)])
    assert r.exit_code == 0, r.output
    assert load_chain(elsewhere / "posterior" / "chain.h5").n_steps == 20
    assert not (elsewhere / "params.json").exists()


def test_committed_daylight_posterior_converged_and_covers_the_truth():
    """reports/eye_daylight/posterior: `invglare sample fits/eye_daylight.toml` as committed."""
    folder = Path(__file__).resolve().parents[2] / "reports" / "eye_daylight" / "posterior"
    for name in ("summary.md", "corner.png", "trace.png", "predictive.png", "chain.h5"):
        assert (folder / name).is_file(), name
    summary = json.loads((folder / "summary.json").read_text())
    assert summary["converged"] and summary["n_walkers"] == 32
    taus = [p["tau"] for p in summary["parameters"].values()]
    assert summary["n_steps"] > summary["tau_factor"] * max(taus)
    assert 0.2 < summary["acceptance_fraction"]["mean"] < 0.6
    for path in (
        "model.aperture.pupil.diameter_mm",
        "model.aperture.upper_lashes.count",
        "model.aperture.upper_lashes.mean_angle_deg",
    ):
        assert summary["parameters"][path]["truth_in_95"], path


def test_a_posterior_starts_from_the_nearest_stored_fit(tmp_path, monkeypatch):
    """The stored fit: the report folder's, else the config's own (runs/NAME), else the
    committed reports/NAME; with none, the report folder's (where the fit then runs)."""
    from types import SimpleNamespace

    from invglare.config.fit import stored_fit

    monkeypatch.chdir(tmp_path)
    config = tmp_path / "fits" / "eye.toml"
    config.parent.mkdir()
    config.write_text('[target]\nfile = "photo.exr"\n')
    elsewhere = SimpleNamespace(out_dir=tmp_path / "elsewhere", name="eye", config_path=config)
    own = SimpleNamespace(out_dir=Path("runs") / "eye", name="eye", config_path=config)
    assert stored_fit(own) == Path("runs/eye/params.json")  # none: the fit runs
    committed = Path("reports/eye/params.json")
    committed.parent.mkdir(parents=True)
    committed.write_text("{}")
    assert stored_fit(own) == committed
    assert stored_fit(elsewhere) == committed
    Path("runs/eye").mkdir(parents=True)
    Path("runs/eye/params.json").write_text("{}")
    assert stored_fit(elsewhere) == Path("runs/eye/params.json")
    (elsewhere.out_dir).mkdir()
    (elsewhere.out_dir / "params.json").write_text("{}")
    assert stored_fit(elsewhere) == elsewhere.out_dir / "params.json"


def test_runs_write_under_runs_by_default():
    """A fit's report folder defaults to runs/NAME (git-ignored), never the committed one."""
    from invglare.config.fit import read_fit_section

    ignored = (Path(__file__).resolve().parents[2] / ".gitignore").read_text().split()
    assert "/runs/" in ignored
    name, folder = read_fit_section({}, Path("fits/eye_daylight.toml"), None)
    assert (name, folder) == ("eye_daylight", Path("runs") / "eye_daylight")
    name, folder = read_fit_section({}, Path("fits/eye_daylight.toml"), "reports/eye_daylight")
    assert folder == Path("reports/eye_daylight")
