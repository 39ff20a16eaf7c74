"""The inputs of a batch: photos from globs, folders and tables; populations of synth specs.

Everything here is checked before any worker starts, so each mistake must be one clear
error naming the value: a glob that matches nothing, a table with an unknown column, a
distribution that is not one.
"""

import csv
import math
from pathlib import Path

import numpy as np
import pytest

from invglare.config.batch import PhotoJob, photo_config, read_photos
from invglare.config.population import read_population
from invglare.config.synth import load_synth, load_synth_specs
from invglare.errors import ConfigError


def touch(folder: Path, *names: str) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        (folder / name).write_bytes(b"x")


def test_globs_folders_files_and_tables_give_each_photo_once(tmp_path):
    touch(tmp_path / "a", "p1.exr", "p2.EXR", "notes.txt")
    touch(tmp_path / "b", "q1.tif")
    (tmp_path / "list.csv").write_text(
        "photo,name,pixel_scale_deg,saturation,linear,channel\n"
        "b/q1.tif,subject_q,0.003,60000,true,Y\n"
        "a/p1.exr,,,,,\n"
    )
    jobs = read_photos(["a/*.exr", str(tmp_path / "a"), "list.csv"], cwd=tmp_path)
    # a/p1.exr is named by the glob, the folder and the table: fitted once, first as named.
    assert [j.name for j in jobs] == ["p1", "p2", "subject_q"]
    assert jobs[0].path == tmp_path / "a" / "p1.exr" and jobs[0].target == {}
    assert jobs[2].target == {"pixel_scale_deg": 0.003, "saturation": 60000.0, "linear": True,
                              "channel": "Y"}  # fmt: skip


@pytest.mark.parametrize(
    "sources, match",
    [
        ([], "no photos given"),
        (["missing/*.exr"], r"the glob 'missing/\*\.exr' matches no photo"),
        (["a/*.txt"], r"matches no photo .* it matched 1 other paths"),
        (["empty"], "the folder 'empty' holds no photo"),
        (["nothere.exr"], "the photo 'nothere.exr' does not exist"),
    ],
)
def test_sources_that_name_no_photo_are_refused(tmp_path, sources, match):
    touch(tmp_path / "a", "notes.txt")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ConfigError, match=match):
        read_photos(sources, cwd=tmp_path)


@pytest.mark.parametrize(
    "table, match",
    [
        ("photo,gain\np.exr,2\n", r"unknown column\(s\) 'gain'; valid columns: photo, name"),
        ("name\nx\n", "has no 'photo' column"),
        ("photo\n", "lists no photo"),
        ("", "is empty"),
        ("photo,photo\np.exr,p.exr\n", "names a column twice"),
        ("photo,saturation\np.exr,lots\n", r"line 2: saturation = 'lots' must be a number > 0"),
        ("photo,pixel_scale_deg\np.exr,-1\n", "pixel_scale_deg = '-1' must be a number > 0"),
        ("photo,linear\np.exr,maybe\n", "linear = 'maybe' must be true or false"),
        ("photo\ngone.exr\n", r"line 2: the photo .*gone\.exr does not exist"),
        ("photo,truth\np.exr,t.json\n", r"the truth file .*t\.json does not exist"),
        ("photo,name\np.exr,a b\n", "must be a plain name"),
        ("photo,name\np.exr\n", "1 cells for 2 columns"),
    ],
)
def test_bad_photo_tables_name_the_line_and_column(tmp_path, table, match):
    touch(tmp_path, "p.exr")
    (tmp_path / "photos.csv").write_text(table)
    with pytest.raises(ConfigError, match=match):
        read_photos(["photos.csv"], cwd=tmp_path)


def test_two_photos_with_one_name_are_refused(tmp_path):
    touch(tmp_path / "x", "p.exr")
    touch(tmp_path / "y", "p.exr")
    with pytest.raises(ConfigError, match="would share the report folder 'p'"):
        read_photos(["x/p.exr", "y/p.exr"], cwd=tmp_path)


def test_photo_config_puts_the_photo_in_and_drops_the_configs_own_truth_and_folder():
    config = {
        "fit": {"name": "base", "out_dir": "elsewhere"},
        "target": {"file": "base.exr", "truth": "base.truth.json", "saturation": 6e4},
        "solver": {"n_starts": 3},
    }
    job = PhotoJob("p7", Path("/data/p7.exr"), {"pixel_scale_deg": 0.004})
    out = photo_config(config, job)
    assert out["target"] == {"file": "/data/p7.exr", "saturation": 6e4, "pixel_scale_deg": 0.004}
    assert out["fit"] == {"name": "p7"} and out["solver"] == {"n_starts": 3}
    assert config["target"]["file"] == "base.exr"  # the config itself is left alone
    with pytest.raises(ConfigError, match=r"\[target\] must be a table"):
        photo_config({"target": "p.exr"}, job)


# --------------------------------------------------------------------------------------
# populations


def test_population_draws_are_reproducible_and_follow_their_distributions():
    table = {
        "size": 400,
        "seed": 3,
        "set": {
            "model.aperture.pupil.diameter_mm": ["uniform", 2.5, 4.0],
            "model.aperture.upper_lashes.count": ["integers", 30, 33],
        },
        "observation": {"flux": ["loguniform", 1e6, 1e8], "dx_px": ["normal", 0.1, 0.2]},
        "config": {"model.eye.seed": ["sequence", 1000, 2]},
    }
    draws = read_population(table).draw()
    assert draws == read_population(table).draw()
    d = np.array([m["set"]["model.aperture.pupil.diameter_mm"] for m in draws])
    n = [m["set"]["model.aperture.upper_lashes.count"] for m in draws]
    flux = np.array([m["observation"]["flux"] for m in draws])
    dx = np.array([m["observation"]["dx_px"] for m in draws])
    assert 2.5 <= d.min() and d.max() <= 4.0 and abs(d.mean() - 3.25) < 0.05
    assert set(n) == {30, 31, 32, 33} and all(isinstance(v, int) for v in n)
    # log-uniform: the log's mean is the middle of the log bounds (std of it: 1.33/sqrt(400))
    assert abs(np.log10(flux).mean() - 7.0) < 0.2
    assert abs(dx.mean() - 0.1) < 0.04 and abs(dx.std() - 0.2) < 0.03
    assert [m["config"]["model.eye.seed"] for m in draws[:3]] == [1000, 1002, 1004]


@pytest.mark.parametrize(
    "table, match",
    [
        ({"seed": 1, "set": {"model.x": ["uniform", 0, 1]}}, "needs the key 'size'"),
        ({"size": 0, "set": {"model.x": ["uniform", 0, 1]}}, "size must be >= 1"),
        ({"size": 2}, "draws nothing"),
        ({"size": 2, "set": {"model.x": ["beta", 1, 2]}}, "'beta' is not one of uniform"),
        ({"size": 2, "set": {"model.x": 3.0}}, "must be a distribution"),
        ({"size": 2, "set": {"model.x": ["uniform", 2, 1]}}, "needs low <= high"),
        ({"size": 2, "set": {"model.x": ["uniform", 1]}}, "uniform takes 2 number"),
        ({"size": 2, "set": {"model.x": ["integers", 1.5, 3]}}, "must be integers"),
        ({"size": 2, "set": {"model.x": ["loguniform", 0, 3]}}, "needs low > 0"),
        ({"size": 2, "set": {"pupil": ["uniform", 0, 1]}}, "must start with 'model.'"),
        ({"size": 2, "observation": {"fluxx": ["uniform", 0, 1]}}, "not an observation field"),
        ({"size": 2, "sizes": 3}, "unknown key 'sizes'"),
    ],
)
def test_bad_population_tables_are_refused(table, match):
    with pytest.raises(ConfigError, match=match):
        read_population(table)


SPEC = """
[synth]
model = "model.toml"
seed = 100
out = "crowd"

[set]
"model.aperture.shapes[0].diameter_mm" = 3.0

[population]
size = 3
seed = 9
name = "eye"

[population.set]
"model.aperture.shapes[0].diameter_mm" = ["uniform", 2.5, 3.5]

[population.observation]
flux = ["loguniform", 1e5, 1e6]

[population.config]
"output.npix" = ["sequence", 16, 8]

[observation]
flux = 1e6
gain = 2.0
"""


def test_a_population_spec_gives_its_members(tmp_path):
    (tmp_path / "model.toml").write_text('[model]\nkind = "aperture"\n[output]\nnpix = 32\n')
    spec_path = tmp_path / "crowd.toml"
    spec_path.write_text(SPEC)
    members = load_synth_specs(spec_path)
    assert [m.name for m in members] == ["eye_00", "eye_01", "eye_02"]
    assert [m.seed for m in members] == [100, 101, 102]
    assert all(m.out_dir == tmp_path / "crowd" for m in members)
    assert [m.model_config["output"]["npix"] for m in members] == [16, 24, 32]
    d = [m.set_values["model.aperture.shapes[0].diameter_mm"] for m in members]
    assert len(set(d)) == 3 and all(2.5 <= v <= 3.5 for v in d)
    assert all(1e5 <= m.observation["flux"] <= 1e6 and m.observation["gain"] == 2.0
               for m in members)  # fmt: skip
    assert members[1].drawn["output.npix"] == 24
    assert math.isclose(members[0].drawn["flux"], members[0].observation["flux"])
    with pytest.raises(ConfigError, match="describes a population"):
        load_synth(spec_path)
    spec_path.write_text(SPEC.replace('"output.npix"', '"nothing.npix"'))
    with pytest.raises(ConfigError, match=r"population.config.'nothing.npix'"):
        load_synth_specs(spec_path)


def test_the_bundled_population_table_lists_every_member():
    """data_synthetic/eye_population/: each drawn value in population.csv is its photo's
    truth (the truth files are what the batch fit reads)."""
    import json

    from invglare.config.model import build_model
    from invglare.files.toml import load_toml

    root = Path(__file__).resolve().parents[2]
    folder = root / "data_synthetic" / "eye_population"
    with open(folder / "population.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 16
    # Each eye's random draw is its own, and not the fit model's (seed 7).
    fit_model = build_model(load_toml(root / "examples" / "eye_population.toml"), root / "examples")
    keys = {tuple(fit_model.to_config()["model"]["eye"]["lashes_upper"]["key_data"])}
    for row in rows:
        truth = json.loads((folder / row["photo"].replace(".exr", ".truth.json")).read_text())
        assert truth["drawn"]["model.aperture.pupil.diameter_mm"] == float(
            row["model.aperture.pupil.diameter_mm"]
        )
        assert truth["set"]["model.aperture.upper_lashes.count"] == int(
            row["model.aperture.upper_lashes.count"]
        )
        assert truth["drawn"]["model.eye.seed"] == int(row["model.eye.seed"]) != 7
        assert truth["noise_seed"] == int(row["noise_seed"])
        keys.add(tuple(truth["model"]["model"]["eye"]["lashes_upper"]["key_data"]))
    assert len(keys) == 17
