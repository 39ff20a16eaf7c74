"""One path language for parameters: model-config keys as paths, the aperture's one name,
the older spellings (with a DeprecationWarning once per spelling), and the readers."""

import dataclasses
import math
import warnings
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from jaxtyping import Array, Float

from invglare.config import fit_tables
from invglare.config.model import build_model
from invglare.config.paths import PREFIXES, config_key_to_path, get_key, path_to_config_key
from invglare.errors import ConfigError
from invglare.files.toml import load_toml
from invglare.fit import Forward, Observation, Parameter, ParameterSpace, valid_paths
from invglare.fit import paths as paths_module
from invglare.fit.paths import read_path, spelling, static_int
from invglare.models.kakimoto import KakimotoGlare
from invglare.models.temporal import TemporalGlare

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


@pytest.fixture(autouse=True)
def _fresh_warnings(monkeypatch):
    """Each test sees the first use of every old spelling (they warn once per process)."""
    monkeypatch.setattr(paths_module, "_WARNED", set())
    monkeypatch.setattr(fit_tables, "_WARNED", set())


class Part(eqx.Module):
    diameter_mm: Float[Array, ""] = eqx.field(converter=jnp.asarray)
    n_blades: int = eqx.field(static=True, default=6)


class HoldsEye(eqx.Module):
    """Holds its aperture in a field `eye` and renders it with a method `aperture()`, as
    the temporal model does."""

    eye: Part

    def aperture(self):
        return jnp.ones((4, 4)) * self.eye.diameter_mm

    def __call__(self):
        return self.aperture()


class HoldsAperture(eqx.Module):
    aperture: Part

    def __call__(self):
        return jnp.ones((4, 4)) * self.aperture.diameter_mm


def test_the_models_store_the_aperture_under_the_two_names_the_alias_joins():
    kakimoto = {f.name for f in dataclasses.fields(KakimotoGlare)}
    temporal = {f.name for f in dataclasses.fields(TemporalGlare)}
    assert "aperture" in kakimoto and "eye" not in kakimoto
    assert "eye" in temporal and "aperture" not in temporal
    assert paths_module.FIELD_ALIASES == {"aperture": ("eye",)}


def test_model_aperture_names_the_aperture_of_every_model():
    """The same path reads and writes the pupil whichever field holds it; valid paths and
    spellings come in the new language; no warning for it."""
    new = "model.aperture.diameter_mm"
    for model in (HoldsEye(Part(3.0)), HoldsAperture(Part(3.0))):
        fwd = Forward(model, Observation())
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert spelling(fwd, new) == new
            assert read_path(fwd, new) == 3.0
            assert new in valid_paths(fwd) and "model.eye.diameter_mm" not in valid_paths(fwd)
            space = ParameterSpace([Parameter(new, 1.0, 5.0, init=2.0)])
            moved = space.apply(fwd, jnp.asarray([4.5]))
        assert read_path(moved, new) == 4.5
        np.testing.assert_array_equal(np.asarray(moved.model()), 4.5)
        assert static_int(fwd, "model.aperture.n_blades") == 6


def test_the_older_spelling_model_eye_warns_once_and_names_the_same_value():
    fwd = Forward(HoldsEye(Part(3.0)), Observation())
    old, new = "model.eye.diameter_mm", "model.aperture.diameter_mm"
    with pytest.warns(DeprecationWarning, match=f"write '{new}'") as caught:
        assert spelling(fwd, old) == new
    assert len([w for w in caught if issubclass(w.category, DeprecationWarning)]) == 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # once per spelling: quiet from now on
        space = ParameterSpace([Parameter(old, 1.0, 5.0, init=2.0)])
        assert read_path(space.apply(fwd, jnp.asarray([4.0])), new) == 4.0
    # Two spellings of one value are one parameter freed twice.
    both = ParameterSpace([Parameter(old, 1.0, 5.0, init=2.0), Parameter(new, 1.0, 5.0, init=2.0)])
    with pytest.raises(ConfigError, match="name the same value"):
        both.check(fwd)
    # On a model whose field is `aperture`, `eye` is no spelling of anything.
    with pytest.raises(ConfigError, match="does not exist"):
        spelling(Forward(HoldsAperture(Part(3.0)), Observation()), old)


def test_the_free_and_stage_readers_keep_the_new_spelling():
    fwd = Forward(HoldsEye(Part(3.0)), Observation())
    table = {"path": "model.eye.diameter_mm", "lower": 1.0, "upper": 5.0}
    with pytest.warns(DeprecationWarning, match="older spelling"):
        params, nuisance, _ = fit_tables.read_free([table], fwd, {})
    assert [p.path for p in params] == ["model.aperture.diameter_mm"] and not nuisance
    assert params[0].init == 3.0  # the model's value
    paths = ("model.aperture.diameter_mm", "obs.flux")
    stage = {"views": {"radial": 1.0}, "fixed": ["model.eye.diameter_mm"]}
    (read,) = fit_tables.read_stages([stage], 10, fwd, paths)
    assert read.fixed == ("model.aperture.diameter_mm",)
    with pytest.raises(ConfigError, match=r"fixed names 'obs\.gain', which is not a free"):
        fit_tables.read_stages([{"views": {"radial": 1.0}, "fixed": ["obs.gain"]}], 10, fwd, paths)
    # A branch names a free parameter in any spelling, with distinct integer offsets.
    stage = {"views": {"radial": 1.0}, "branch": {"model.eye.diameter_mm": [-1, 0, 1]}}
    (read,) = fit_tables.read_stages([stage], 10, fwd, paths)  # warned once above
    assert read.branch == (("model.aperture.diameter_mm", (-1, 0, 1)),)
    with pytest.raises(ConfigError, match=r"branch names 'obs\.gain', which is not a free"):
        fit_tables.read_stages([{"views": {"radial": 1.0}, "branch": {"obs.gain": [0]}}], 10, fwd,
                               paths)  # fmt: skip
    for bad in ([], [0, 0], [0.5], [True], 1):
        stage = {"views": {"radial": 1.0}, "branch": {"obs.flux": bad}}
        with pytest.raises(ConfigError, match=r"branch\.obs\.flux must be a list of distinct"):
            fit_tables.read_stages([stage], 10, fwd, paths)


@pytest.mark.parametrize(
    ("kind", "key", "path"),
    [
        ("eye", "model.eye.pupil.diameter_mm", "model.aperture.pupil.diameter_mm"),
        ("eye", "model.eye.lashes_upper.n_max", "model.aperture.upper_lashes.n_max"),
        ("eye", "model.eye.lashes_lower.count", "model.aperture.lower_lashes.count"),
        ("eye", "model.eye.particles.1.count", "model.aperture.particles[1].count"),
        ("camera", "model.camera.diaphragm.n_blades", "model.aperture.diaphragm.n_blades"),
        ("camera", "model.camera.cross_screen.spacing_mm", "model.aperture.filter.spacing_mm"),
        ("aperture", "model.shapes.0.diameter_mm", "model.aperture.shapes[0].diameter_mm"),
        ("temporal", "model.eye.lids.upper_opening_mm", "model.aperture.lids.upper_opening_mm"),
        ("temporal", "model.luminance_scale", "model.luminance_scale"),
        ("veiling", "model.lens.sensor_reflectance", "model.ghosts.lens.sensor_reflectance"),
        ("veiling", "model.light_angle_deg", "model.light_angle_deg"),
    ],
)
def test_config_keys_and_paths_translate_both_ways(kind, key, path):
    assert config_key_to_path(kind, key) == path
    assert path_to_config_key(kind, path) == key


#: Keys of the bundled model configs (below ``model.``) and the examples they are in.
CONFIG_KEYS = {
    "eye_night.toml": (
        "eye.pupil.diameter_mm", "eye.gratings.spacing_mm", "eye.particles.1.count",
        "eye.particles.1.n_max", "eye.lids.lower_opening_mm", "eye.gratings.lines_per_grating",
    ),
    "false_lashes_camera.toml": (
        "eye.lashes_upper.count", "eye.lashes_upper.n_max", "eye.lashes_upper.length_mm",
        "obstacle_distance_mm",
    ),
    "camera_cross_screen.toml": (
        "camera.diaphragm.n_blades", "camera.diaphragm.f_number",
        "camera.cross_screen.spacing_mm", "camera.cross_screen.duty_cycle",
    ),
    "pupil_with_lashes.toml": ("shapes.0.diameter_mm", "shapes.1.thickness_mm"),
}  # fmt: skip


#: Integer choices (static fields); the other keys are float leaves (a count is relaxed).
STATIC = ("n_blades", "n_max", "lines_per_grating")


@pytest.mark.parametrize(("example", "keys"), list(CONFIG_KEYS.items()))
def test_each_config_key_reaches_its_value_in_the_built_model(example, keys):
    """The translation against real models: the value at the path is the config's (a float
    leaf, or an integer choice such as n_blades and n_max)."""
    config = load_toml(EXAMPLES / example)
    kind = config["model"]["kind"]
    fwd = Forward(build_model(config, EXAMPLES, npix=32), Observation())
    for short in keys:
        key = f"model.{short}"
        expected = get_key(config, key, "test")
        path = config_key_to_path(kind, key)
        found = static_int(fwd, path) if short.rsplit(".", 1)[-1] in STATIC else None
        if found is None:
            found = read_path(fwd, path)
        assert found == pytest.approx(expected, rel=1e-6), (key, path)
    assert set(PREFIXES) == {"aperture", "eye", "camera", "temporal", "veiling"}


def test_discrete_paths_name_integer_choices_only():
    fwd = Forward(HoldsAperture(Part(3.0)), Observation())
    config = {"model": {"kind": "camera", "camera": {"n_blades": 6}}}
    with pytest.raises(ConfigError, match="is a fitted value"):
        fit_tables.read_discrete(
            [{"path": "model.aperture.diameter_mm", "values": [3]}], config, fwd
        )
    with pytest.raises(
        ConfigError, match=r"integer choices of this model: model\.aperture\.n_blades"
    ):
        fit_tables.read_discrete([{"path": "model.aperture.n_blade", "values": [5]}], config, fwd)
    with pytest.raises(ConfigError, match="needs a path"):
        fit_tables.read_discrete(
            [{"path": "model.aperture.n_blades", "key": "model.camera.n_blades", "values": [5]}],
            config,
            fwd,
        )
    (option,) = fit_tables.read_discrete(
        [{"path": "model.aperture.n_blades", "values": [5, 6]}], config, fwd
    )
    assert (option.path, option.key, option.values) == (
        "model.aperture.n_blades", "model.camera.n_blades", (5, 6)
    )  # fmt: skip
    with pytest.warns(DeprecationWarning, match="path = 'model.aperture.n_blades'"):
        (old,) = fit_tables.read_discrete(
            [{"key": "model.camera.n_blades", "values": [5, 6]}], config, fwd
        )
    assert old == option
    assert math.isfinite(read_path(fwd, "obs.flux"))
