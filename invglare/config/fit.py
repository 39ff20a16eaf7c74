"""Fit configurations: a photo, a model, the free parameters, views and solver settings.

``invglare fit`` and ``invglare sample`` read the same TOML file through
:func:`load_fit`, which checks everything that can be checked before any
solving (keys, paths, bounds, the photo) and returns a :class:`FitSetup`.
Relative paths are relative to the config file.

```toml
[fit]
name = "eye_daylight"            # default: the file's stem
out_dir = "../reports/eye_daylight"  # default: reports/NAME under the current folder

[target]
file = "../data_synthetic/eye_daylight.exr"   # linear photo in counts (EXR or float TIFF)
pixel_scale_deg = 0.003          # default: the EXR header's pixelScaleDeg
saturation = 60000.0             # clip level in counts; omit if nothing clipped
channel = "Y"                    # which channel of a multi-channel file
linear = false                   # true: accept an integer file known to hold linear counts
truth = "eye_daylight.truth.json"  # ground truth; default NAME.truth.json beside the photo

[model]
config = "../examples/eye_daylight.toml"   # model config; built on the photo's grid
wavelength_nm = 550.0            # optional: override the config's (one) wavelength

[observation]                    # fixed observation values (invglare.fit.Observation)
gain = 2.0                       # flux and background default to guesses from the photo
read_noise = 3.0

[[free]]                         # one table per free parameter
path = "model.aperture.pupil.diameter_mm"
lower = 2.0
upper = 4.5
init = 3.3                       # or a range [2.5, 4.0] the starts are drawn from;
                                 # default: the model's value (flux, background: the guess)
prior = "uniform"                # or ["normal", mean, std], ["lognormal", mean_log, std_log]
transform = "auto"               # auto, log, logit, identity
nuisance = false                 # default: true for "obs.*" paths (kept at init in every start)

[[discrete]]                     # a static choice (integer) tried value by value
key = "model.camera.diaphragm.n_blades"   # a key of the *model config*, dotted
values = [5, 6, 7, 8]

[views]                          # name = weight: pixels, log, radial, angular, halo
pixels = 1.0

[view_options.angular]           # options of a view (see invglare.fit.views)
n_bins = 72

[[stage]]                        # optional stages run before the final one, in order, each
views = { radial = 1.0, angular = 1.0 }   # from the best result of the one before: e.g.
max_steps = 40                   # draw-independent statistics first, to reach the right
                                 # basin before fitting pixel by pixel ([views], [solver])
fixed = ["obs.dx_px", "obs.dy_px"]  # held at their start values in this stage

[solver]
solver = "lm"                    # lm (Levenberg-Marquardt) or bfgs
n_starts = 3                     # starts drawn across the bounds (Latin hypercube)
seed = 0                         # of the starts
scan = 64                        # optional: score 64 points across the bounds with the first
                                 # stage's views (no solving) and start from the best n_starts
coarse_to_fine = [1]             # block sizes of the stages, ending with 1
refine_top = 1
max_steps = 100
rtol = 1e-6
atol = 1e-8
covariance_scale = "chi2"        # chi2, absolute or a number
batch = "vmap"                   # vmap (all starts at once) or loop
```

**Example:**

```python
import jax
from invglare.fit import fit
from invglare.config.fit import load_fit

with jax.enable_x64(True):               # fits are meant to run in float64
    setup = load_fit("fits/eye_daylight.toml")
    result = fit(setup.space, setup.forward, setup.target, setup.views, **setup.fit_kwargs())
```
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import json
import math
import os
import re
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from invglare.config.section import Section, check_sections
from invglare.config.synth import read_observation, truth_path_for
from invglare.errors import ConfigError, InputDataError
from invglare.files.toml import load_toml

#: [sample] belongs to ``invglare sample`` (read by invglare.commands.sample); a fit ignores it.
SECTIONS = ("fit", "target", "model", "observation", "free", "discrete", "views", "view_options",
            "stage", "solver", "sample")  # fmt: skip
STAGE_KEYS = ("views", "max_steps", "fixed")
FREE_KEYS = ("path", "lower", "upper", "init", "prior", "transform", "nuisance")
DISCRETE_KEYS = ("key", "values")
_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")


@dataclasses.dataclass(frozen=True)
class DiscreteOption:
    """A static (integer) choice of the model config tried value by value.

    `key` is a dotted key into the model config (``"model.camera.diaphragm.n_blades"``),
    `values` the candidates, `truth` the value in the ground truth (None if unknown).
    """

    key: str
    values: tuple[int, ...]
    truth: int | None = None


@dataclasses.dataclass(frozen=True)
class Stage:
    """A stage run before the final fit: its views, step budget and the paths it holds fixed.

    Stochastic structure (lash and needle positions) makes the pixel-wise objective
    multimodal; a first stage on views that do not depend on the random draw (radial
    profile, angular energy) brings the starts into the right basin for the final
    pixel-wise stage. Such views hardly constrain some nuisances (the source centre):
    `fixed` holds them at the values the stage starts from.
    """

    views: dict[str, float]
    max_steps: int
    fixed: tuple[str, ...] = ()


@dataclasses.dataclass
class FitSetup:
    """Everything a fit of a photo needs, checked (see :func:`load_fit`).

    **Fields:**

    - `name`, `config_path`: the fit's name and its config file.
    - `target`, `target_path`: the photo (float64 counts, ``(h, w)``) and its file.
    - `pixel_scale_deg`: the photo's pixel scale the model is built at (deg/px).
    - `forward`: the ``Forward(model, obs)`` template holding every fixed value.
    - `space`: the free parameters (:class:`~invglare.fit.ParameterSpace`).
    - `starts`: ``(n_starts, p)`` physical starting values, in the order of `space.paths`.
    - `views`, `view_options`: ``{name: weight}`` of the final stage and
      ``{name: {option: value}}`` of every view used.
    - `stages`: the :class:`Stage` s run before the final one (often none).
    - `solver`: keyword arguments of :func:`invglare.fit.fit` (solver, max_steps, rtol,
      atol, coarse_to_fine, refine_top, covariance_scale, batch).
    - `seed`: seed of the starts.
    - `scan`: 0, or how many points across the bounds are scored (by the first stage's
      views) to pick the `n_starts` best as the starts.
    - `discrete`: the static choices to sweep (:class:`DiscreteOption`).
    - `truth`, `truth_path`: ``{path: value}`` of the free parameters in the ground
      truth, and the file it came from (None for a real photo).
    - `out_dir`: where the report goes.
    - `model_config`, `model_path`, `wavelength_nm`: how the model is built (for
      :meth:`forward_for`).
    """

    name: str
    config_path: Path
    target: np.ndarray
    target_path: Path
    pixel_scale_deg: float
    forward: Any
    space: Any
    starts: np.ndarray
    views: dict[str, float]
    view_options: dict[str, dict[str, Any]]
    solver: dict[str, Any]
    seed: int
    stages: tuple[Stage, ...]
    scan: int
    discrete: tuple[DiscreteOption, ...]
    truth: dict[str, float] | None
    truth_path: Path | None
    out_dir: Path
    model_config: dict[str, Any]
    model_path: Path
    wavelength_nm: float | None = None
    init_ranges: dict[int, tuple[float, float]] = dataclasses.field(default_factory=dict)

    def draw_starts(self, n: int) -> np.ndarray:
        """`n` starts across the bounds, as `starts` was drawn (the config's seed)."""
        return draw_starts(self.space, self.init_ranges, n, self.seed)

    def fit_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of :func:`invglare.fit.fit` but space, forward, target and views."""
        return {
            **self.solver,
            "starts": self.starts,
            "n_starts": int(self.starts.shape[0]),
            "view_options": self.view_options or None,
            "truth": self.truth,
        }

    def candidates(self) -> list[dict[str, int]]:
        """Every combination of the discrete choices (``[{}]`` when there are none)."""
        if not self.discrete:
            return [{}]
        keys = [d.key for d in self.discrete]
        return [
            dict(zip(keys, combo, strict=True))
            for combo in itertools.product(*(d.values for d in self.discrete))
        ]

    def truth_model(self):
        """The model of the ground truth file (as the photo was made), or None without one."""
        if self.truth_path is None:
            return None
        from invglare.config.model import build_model

        data = json.loads(self.truth_path.read_text(encoding="utf-8"))
        return build_model(data["model"], self.truth_path.parent, source=str(self.truth_path))

    def forward_for(self, choice: Mapping[str, int]):
        """The forward template with the model rebuilt for one discrete `choice`."""
        from invglare.fit import Forward

        if not choice:
            return self.forward
        config = copy.deepcopy(self.model_config)
        for key, value in choice.items():
            _set_key(config, key, value)
        model = _build(config, self.model_path, self.target.shape, self.pixel_scale_deg,
                       self.wavelength_nm)  # fmt: skip
        forward = Forward(model, self.forward.obs)
        self.space.check(forward)
        return forward


# --------------------------------------------------------------------------------------
# helpers


def _number(value: Any, where: str, allow_inf: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(f"{where} must be a number, got {value!r}")
    v = float(value)
    if math.isnan(v) or (not allow_inf and math.isinf(v)):
        raise ConfigError(f"{where} must be a finite number, got {value!r}")
    return v


def _resolve(base: Path, value: str) -> Path:
    p = Path(value).expanduser()
    return Path(os.path.normpath(p if p.is_absolute() else base / p))


def _step(node: Any, part: str) -> Any:
    """One step of a dotted config key: a table key, or a list index (``shapes.0``)."""
    if isinstance(node, Mapping) and part in node:
        return node[part]
    if isinstance(node, list) and part.isdigit() and int(part) < len(node):
        return node[int(part)]
    raise KeyError(part)


def _get_key(config: Mapping[str, Any], key: str, where: str) -> Any:
    node: Any = config
    for part in key.split("."):
        try:
            node = _step(node, part)
        except KeyError:
            raise ConfigError(
                f"{where}: the model config has no key {key!r} (stopped at {part!r}); "
                "discrete choices are keys of the model config, e.g. "
                "'model.camera.diaphragm.n_blades' or 'model.shapes.0.n_blades'"
            ) from None
    return node


def _set_key(config: dict[str, Any], key: str, value: Any) -> None:
    parts = key.split(".")
    node: Any = config
    for part in parts[:-1]:
        node = _step(node, part)
    if isinstance(node, list):
        node[int(parts[-1])] = value
    else:
        node[parts[-1]] = value


def _build(
    config, model_path: Path, shape: tuple[int, ...], scale: float, wavelength_nm: float | None
):
    from invglare.config.model import build_model

    # A veiling model draws any screen; the PSF models' output grids are square (a
    # non-square photo is refused where the photo is read).
    veiling = config.get("model", {}).get("kind") == "veiling"
    return build_model(
        config,
        model_path.parent,
        npix=(int(shape[0]), int(shape[1])) if veiling else int(shape[0]),
        pixel_scale_deg=scale,
        wavelengths_nm=wavelength_nm,
        source=str(model_path),
    )


# --------------------------------------------------------------------------------------
# the photo


def load_target(
    path: Path,
    *,
    channel: str | None = None,
    linear: bool = False,
    saturation: float | None = None,
    square: bool = True,
) -> tuple[np.ndarray, float | None]:
    """Read a target photo as float64 counts; **returns** ``(image, pixelScaleDeg or None)``.

    Refuses (:class:`~invglare.errors.InputDataError`, with the reason) a missing or
    unreadable file, a display-encoded integer image (8-bit PNG/JPEG, integer TIFF:
    tone-mapped, not linear counts) unless `linear`, a float image that looks
    tone-mapped (every value a multiple of 1/255 in [0, 1]) unless `linear`, a
    multi-channel image without `channel`, a non-square image (when `square`: the PSF
    models' grids are square, the veiling model's screen is not), NaN/inf pixels, an
    image that is all zeros or constant, and one whose every pixel is at `saturation`.
    """
    from invglare.files.images import read_image
    from invglare.fit.observation import check_target

    if not path.exists():
        raise InputDataError(f"target photo {path} does not exist")
    image = read_image(path, allow_negative=True)
    data = np.asarray(image.data, dtype=np.float64)
    if image.display_encoded:
        if not linear:
            depth = f"{image.bit_depth}-bit " if image.bit_depth else ""
            raise InputDataError(
                f"target photo {path} is a {depth}{path.suffix.lstrip('.').upper()} image, "
                "display-encoded (gamma / tone-mapped), not linear counts; fit a linear photo "
                "(raw converted to OpenEXR or float TIFF), or set target.linear = true if this "
                "file is known to hold linear values"
            )
        # Integer codes were scaled to [0, 1] on reading; a linear file's counts are the codes.
        data = data * float(2 ** (image.bit_depth or 8) - 1)
    if data.ndim == 3:
        names = list(image.channels)
        if channel is None:
            raise InputDataError(
                f"target photo {path} has channels {', '.join(names)}; choose one with "
                "target.channel (fits use one monochrome channel)"
            )
        if channel not in names:
            raise InputDataError(
                f"target photo {path} has no channel {channel!r}; it has {', '.join(names)}"
            )
        data = data[..., names.index(channel)]
    elif channel is not None and channel not in image.channels:
        raise InputDataError(
            f"target photo {path} has no channel {channel!r}; it has {', '.join(image.channels)}"
        )
    if data.ndim != 2 or (square and data.shape[0] != data.shape[1]):
        raise InputDataError(
            f"target photo {path} is {data.shape[1]}x{data.shape[0]} pixels; crop it to a "
            "square centred on the light source (the model's output grid is square)"
        )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            data = check_target(data, saturation=saturation).astype(np.float64)
        except InputDataError as err:
            raise InputDataError(f"target photo {path}: {err}") from None
    for w in caught:
        if "tone-mapped" in str(w.message) and not linear:
            raise InputDataError(
                f"target photo {path}: {w.message}; set target.linear = true if it is linear"
            )
    return data, image.pixel_scale_deg


# --------------------------------------------------------------------------------------
# the config


def centre_guess(
    target: np.ndarray, background: float = 0.0, radius_px: float = 12.0
) -> dict[str, float]:
    """``{"obs.dx_px", "obs.dy_px"}``: the source centre from the photo's bright core.

    The centroid (above background) of the pixels within `radius_px` of pixel
    ``(w // 2, h // 2)`` that are brighter than half the peak there, relative to that
    pixel: for a clipped core it is the clipped disk's centre (bright features farther
    out, such as a filter's diffraction orders, are left out). A start within a pixel of
    the truth keeps the centre out of the other parameters' way.
    """
    t = np.asarray(target, dtype=np.float64) - background
    h, wd = t.shape
    rows, cols = np.indices(t.shape)
    near = (rows - h // 2) ** 2 + (cols - wd // 2) ** 2 <= radius_px**2
    peak = t[near].max()
    if not peak > 0:
        return {}
    w = np.where(near & (t >= 0.5 * peak), t, 0.0)
    total = w.sum()
    return {
        "obs.dx_px": float((w * cols).sum() / total - wd // 2),
        "obs.dy_px": float((w * rows).sum() / total - h // 2),
    }


def _read_free(
    tables: Any, forward: Any, guesses: Mapping[str, float]
) -> tuple[list, list, dict[int, tuple[float, float]]]:
    """Parameters and nuisances of the ``[[free]]`` tables, and the init ranges by index."""
    from invglare.fit.params import Parameter, resolve_path

    if not isinstance(tables, list) or not tables:
        raise ConfigError(
            "the fit has no free parameters; add [[free]] tables with path, lower, upper"
        )
    params, nuisance, ranges = [], [], {}
    entries = []
    for i, table in enumerate(tables):
        where = f"free[{i}]"
        if not isinstance(table, dict):
            raise ConfigError(f"[[free]] entry {i} must be a table, got {table!r}")
        for key in table:
            if key not in FREE_KEYS:
                raise ConfigError(
                    f"{where}: unknown key {key!r}; valid keys: {', '.join(FREE_KEYS)}"
                )
        sec = Section(table, where)
        path = sec.get("path", str, required=True)
        where = f"free[{i}] ({path})"
        # Check the path first: its error lists the valid paths.
        steps, index = resolve_path(forward, path)
        lower = _number(sec.get("lower", (int, float), required=True), f"{where}.lower", True)
        upper = _number(sec.get("upper", (int, float), required=True), f"{where}.upper", True)
        init_raw = sec.get("init", (int, float, list), None)
        prior = sec.get("prior", (str, list, dict), None)
        transform = sec.get("transform", str, "auto")
        is_nuisance = sec.get("nuisance", bool, path.startswith("obs."))
        if isinstance(init_raw, list):
            if len(init_raw) != 2:
                raise ConfigError(
                    f"{where}.init must be a number or a range [low, high], got {init_raw!r}"
                )
            lo, hi = (_number(v, f"{where}.init") for v in init_raw)
            if not (lower <= lo < hi <= upper):
                raise ConfigError(
                    f"{where}: the init range [{lo:g}, {hi:g}] must be increasing and lie "
                    f"inside the bounds [{lower:g}, {upper:g}]"
                )
            init = 0.5 * (lo + hi)
            ranges[len(entries)] = (lo, hi)
        elif init_raw is not None:
            init = _number(init_raw, f"{where}.init")
        elif path in guesses:
            init = float(guesses[path])
            if math.isfinite(lower) and math.isfinite(upper):
                # A guess on or outside a bound would be an invalid start: keep it inside.
                margin = 0.01 * (upper - lower)
                init = min(max(init, lower + margin), upper - margin)
        else:
            from invglare.fit.params import _getter

            leaf = _getter(steps)(forward)
            init = float(np.asarray(leaf)[index] if index else np.asarray(leaf))
            if not (lower < init < upper) and math.isfinite(lower) and math.isfinite(upper):
                init = 0.5 * (lower + upper)
        try:
            param = Parameter(path, lower, upper, init=init, prior=prior, transform=transform)
        except TypeError as err:  # a prior table with unknown keys
            raise ConfigError(
                f"{where}.prior must be 'uniform', [kind, mean, std] or a table with kind, mean, "
                f"std; got {prior!r} ({err})"
            ) from None
        entries.append((param, is_nuisance))
    # Parameters of interest first (their starts are spread), nuisances after; the init
    # ranges follow their parameter to its new index.
    order = [k for k, (_, n) in enumerate(entries) if not n] + [
        k for k, (_, n) in enumerate(entries) if n
    ]
    moved = {}
    for new, old in enumerate(order):
        param, is_nuisance = entries[old]
        (nuisance if is_nuisance else params).append(param)
        if old in ranges:
            moved[new] = ranges[old]
    return params, nuisance, moved


def _read_discrete(tables: Any, model_config: Mapping[str, Any]) -> list[DiscreteOption]:
    if tables is None:
        return []
    if not isinstance(tables, list):
        raise ConfigError(f"[[discrete]] must be a list of tables, got {tables!r}")
    out = []
    for i, table in enumerate(tables):
        where = f"discrete[{i}]"
        sec = Section(table, where)
        key = sec.get("key", str, required=True)
        values = sec.get("values", list, required=True)
        sec.finish()
        current = _get_key(model_config, key, where)
        if isinstance(current, bool) or not isinstance(current, int):
            raise ConfigError(
                f"{where}: the model config's {key!r} is {current!r}, not an integer; "
                "continuous values are fitted as [[free]] parameters"
            )
        if not values or not all(isinstance(v, int) and not isinstance(v, bool) for v in values):
            raise ConfigError(f"{where}.values must be a non-empty list of integers, got {values}")
        if len(set(values)) != len(values):
            raise ConfigError(f"{where}.values lists a value twice: {values}")
        out.append(DiscreteOption(key, tuple(values)))
    return out


def _read_truth(
    path: Path, space, forward, discrete: list[DiscreteOption], scale_deg: float
) -> tuple[dict[str, float], list[DiscreteOption]]:
    """Truth of each free path, resolved on the forward rebuilt from a ``*.truth.json``."""
    from invglare.config.model import build_model
    from invglare.fit import Forward, Observation
    from invglare.fit.params import _getter, resolve_path

    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        model_cfg, obs_cfg = data["model"], data["observation"]
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise InputDataError(
            f"ground truth {path} is not a readable synth truth file: {err}"
        ) from None
    truth_model = build_model(model_cfg, path.parent, source=str(path))
    truth_fwd = Forward(truth_model, Observation(**obs_cfg))
    truth = {}
    for p in space.all:
        try:
            steps, index = resolve_path(truth_fwd, p.path, p.steps)
        except ConfigError:
            continue  # a parameter the true model does not have: no truth for it
        leaf = np.asarray(_getter(steps)(truth_fwd))
        value = float(leaf[index] if index else leaf)
        if p.path == "obs.pixel_scale_ratio":
            # The ratio is model scale / photo scale: the fit's model is built at
            # `scale_deg`, the truth's at its own scale.
            value *= scale_deg / float(truth_model.pixel_scale_deg)
        truth[p.path] = value
    resolved = []
    for d in discrete:
        try:
            value = _get_key(data["model"], d.key, "truth")
        except ConfigError:
            value = None
        resolved.append(dataclasses.replace(d, truth=value if isinstance(value, int) else None))
    return truth, resolved


def _read_views(table: Any, where: str) -> dict[str, float]:
    from invglare.fit.views import VIEWS

    if not isinstance(table, dict) or not table:
        raise ConfigError(f"{where} must be a table of name = weight, e.g. pixels = 1.0")
    views = {}
    for view, weight in table.items():
        if view not in VIEWS:
            raise ConfigError(
                f"{where} names unknown view {view!r}; valid views: {', '.join(VIEWS)}"
            )
        w = _number(weight, f"{where} {view}")
        if w < 0:
            raise ConfigError(f"{where} weight of {view!r} must be >= 0, got {w:g}")
        views[view] = w
    return views


def _read_stages(tables: Any, default_steps: int, paths: tuple[str, ...]) -> tuple[Stage, ...]:
    if tables is None:
        return ()
    if not isinstance(tables, list):
        raise ConfigError(f"[[stage]] must be a list of tables, got {tables!r}")
    out = []
    for i, table in enumerate(tables):
        where = f"stage[{i}]"
        sec = Section(table, where)
        views = _read_views(sec.get("views", dict, required=True), f"{where}.views")
        steps = sec.get("max_steps", int, default_steps)
        fixed = sec.get("fixed", list, [])
        sec.finish()
        if steps < 1:
            raise ConfigError(f"{where}.max_steps must be >= 1, got {steps}")
        for path in fixed:
            if path not in paths:
                raise ConfigError(
                    f"{where}.fixed names {path!r}, which is not a free parameter "
                    f"({', '.join(paths)})"
                )
        if len(set(fixed)) >= len(paths):
            raise ConfigError(f"{where}.fixed holds every free parameter; nothing is left to fit")
        out.append(Stage(views, steps, tuple(fixed)))
    return tuple(out)


def _read_solver(table: Any) -> tuple[dict[str, Any], int, int]:
    from invglare.fit.solve import BATCH_MODES, SOLVERS

    sec = Section(table, "solver")
    solver = {
        "solver": sec.choice("solver", SOLVERS, "lm"),
        "max_steps": sec.get("max_steps", int, 100),
        "rtol": sec.get("rtol", float, 1e-6),
        "atol": sec.get("atol", float, 1e-8),
        "coarse_to_fine": tuple(sec.get("coarse_to_fine", list, [1])),
        "refine_top": sec.get("refine_top", int, 1),
        "batch": sec.choice("batch", BATCH_MODES, "vmap"),
    }
    scale = sec.get("covariance_scale", (str, float), "chi2")
    if isinstance(scale, str) and scale not in ("chi2", "absolute"):
        raise ConfigError(f"solver.covariance_scale = {scale!r} is not chi2, absolute or a number")
    solver["covariance_scale"] = scale
    n_starts = sec.get("n_starts", int, 3)
    seed = sec.get("seed", int, 0)
    solver["scan"] = sec.get("scan", int, 0)
    sec.finish()
    if solver["scan"] and solver["scan"] < n_starts:
        raise ConfigError(
            f"solver.scan = {solver['scan']} must be 0 (off) or at least n_starts = {n_starts}"
        )
    factors = solver["coarse_to_fine"]
    if (
        not factors
        or factors[-1] != 1
        or any(isinstance(f, bool) or not isinstance(f, int) or f < 1 for f in factors)
    ):
        raise ConfigError(
            f"solver.coarse_to_fine must be integers >= 1 ending with 1, e.g. [2, 1]; got "
            f"{list(factors)}"
        )
    if n_starts < 1:
        raise ConfigError(f"solver.n_starts must be >= 1, got {n_starts}")
    if solver["max_steps"] < 1:
        raise ConfigError(f"solver.max_steps must be >= 1, got {solver['max_steps']}")
    return solver, n_starts, seed


def draw_starts(space, ranges: Mapping[int, tuple[float, float]], n: int, seed: int) -> np.ndarray:
    """`n` physical starts across the bounds (a Latin hypercube, nuisances at their init).

    Parameters with an init range are drawn stratified within it instead.
    """
    import jax

    key_bounds, key_ranges = jax.random.split(jax.random.key(seed))
    starts = np.array(space.from_latent(space.sample_starts(key_bounds, n)), dtype=np.float64)
    rng = np.random.default_rng(np.asarray(jax.random.key_data(key_ranges)))
    for col, (lo, hi) in ranges.items():
        u = (rng.permutation(n) + rng.uniform(size=n)) / n
        starts[:, col] = lo + (hi - lo) * u
    return starts


def read_fit_section(
    config: dict[str, Any], config_path: Path, out_dir: str | Path | None
) -> tuple[str, Path]:
    """The ``[fit]`` table: the fit's name (default the file's stem) and its report folder
    (`out_dir` if given, else ``fit.out_dir`` relative to the config, else reports/NAME)."""
    sec = Section(config.get("fit", {}), "fit")
    name = sec.get("name", str, config_path.stem)
    out_cfg = sec.get("out_dir", str, None)
    sec.finish()
    if not _NAME.match(name):
        raise ConfigError(f"fit.name = {name!r} must be a plain name (letters, digits, _ - .)")
    if out_dir is not None:
        return name, Path(out_dir)
    if out_cfg is not None:
        return name, _resolve(config_path.parent, out_cfg)
    return name, Path("reports") / name


def load_fit(
    path: str | Path,
    *,
    out_dir: str | Path | None = None,
    n_starts: int | None = None,
    max_steps: int | None = None,
) -> FitSetup:
    """Read a fit config, the photo and the model; check them; return a :class:`FitSetup`.

    **Arguments:**

    - `path`: the fit config (TOML, see the module docstring).
    - `out_dir`: override ``fit.out_dir`` (relative to the current folder).
    - `n_starts`, `max_steps`: override the solver settings.

    The model is built in the current JAX precision: call this inside
    ``jax.enable_x64(True)`` for a float64 fit (as ``invglare fit`` does).

    **Raises:** :class:`~invglare.errors.ConfigError` naming the key for unknown
    tables or keys, a free path that does not exist (listing the valid ones),
    bounds that exclude the initial value, unknown views or options, a model that
    is not monochrome; :class:`~invglare.errors.InputDataError` for a photo that
    cannot be fitted (see :func:`load_target`).
    """
    import equinox as eqx

    from invglare.fit import Forward, Observation, ParameterSpace
    from invglare.fit.views import build_view

    config_path = Path(path)
    config = load_toml(config_path)
    base = config_path.parent
    check_sections(config, SECTIONS, str(config_path))

    name, out = read_fit_section(config, config_path, out_dir)

    tsec = Section(config.get("target", {}), "target")
    target_file = tsec.get("file", str, required=True)
    scale_override = tsec.get("pixel_scale_deg", float, None)
    saturation = tsec.get("saturation", float, None)
    channel = tsec.get("channel", str, None)
    linear = tsec.get("linear", bool, False)
    truth_file = tsec.get("truth", str, None)
    tsec.finish()
    if saturation is not None and not (math.isfinite(saturation) and saturation > 0):
        raise ConfigError(f"target.saturation must be a level > 0 counts, got {saturation!r}")
    msec = Section(config.get("model", {}), "model")
    model_file = msec.get("config", str, required=True)
    wavelength = msec.get("wavelength_nm", float, None)
    msec.finish()
    model_path = _resolve(base, model_file)
    if not model_path.is_file():
        raise ConfigError(f"model.config = {model_file!r}: {model_path} does not exist")
    model_config = load_toml(model_path)

    target_path = _resolve(base, target_file)
    target, header_scale = load_target(
        target_path,
        channel=channel,
        linear=linear,
        saturation=saturation,
        square=model_config.get("model", {}).get("kind") != "veiling",
    )
    scale = scale_override if scale_override is not None else header_scale
    if scale is None:
        raise ConfigError(
            f"the target photo {target_path} has no pixelScaleDeg in its header; set "
            "target.pixel_scale_deg (degrees per pixel)"
        )
    if not (math.isfinite(scale) and scale > 0):
        raise ConfigError(f"target pixel scale must be > 0 deg/px, got {scale!r}")

    model = _build(model_config, model_path, target.shape, scale, wavelength)
    out_shape = eqx.filter_eval_shape(model).shape
    if len(out_shape) != 2:
        raise ConfigError(
            f"{model_path} gives a PSF of shape {out_shape}; fits need a monochrome model: set "
            "[spectrum] wavelengths_nm to one value there, or model.wavelength_nm here"
        )

    obs_fixed = read_observation(config.get("observation", {}))
    if "saturation" in obs_fixed:
        raise ConfigError("give the clip level as target.saturation, not observation.saturation")
    obs_fixed["saturation"] = saturation
    guess = Observation.from_target(target, **obs_fixed)
    forward = Forward(model, guess)
    guesses = {"obs.flux": float(guess.flux), "obs.background": float(guess.background)}
    guesses.update(centre_guess(target, float(guess.background)))

    params, nuisance, ranges = _read_free(config.get("free"), forward, guesses)
    space = ParameterSpace(params, nuisance)
    space.check(forward)
    discrete = _read_discrete(config.get("discrete"), model_config)

    views = _read_views(config.get("views", {"pixels": 1.0}), "[views]")
    solver, n_cfg, seed = _read_solver(config.get("solver", {}))
    scan = solver.pop("scan")
    stages = _read_stages(config.get("stage"), solver["max_steps"], space.paths)
    used = set(views).union(*(st.views for st in stages))
    options = config.get("view_options", {})
    if not isinstance(options, dict):
        raise ConfigError(f"[view_options] must hold one table per view, got {options!r}")
    for view, opts in options.items():
        if view not in used:
            raise ConfigError(
                f"[view_options.{view}] is for a view no stage uses ({', '.join(sorted(used))})"
            )
        if not isinstance(opts, dict):
            raise ConfigError(f"[view_options.{view}] must be a table, got {opts!r}")
    for view in used:  # unknown options fail here, before any model is evaluated
        build_view(view, options.get(view), target.shape, guess, target)

    if n_starts is not None:
        n_cfg = int(n_starts)
    if max_steps is not None:
        solver["max_steps"] = int(max_steps)
        stages = tuple(dataclasses.replace(st, max_steps=int(max_steps)) for st in stages)
    if n_cfg < 1:
        raise ConfigError(f"the number of starts must be >= 1, got {n_cfg}")

    truth_path = _resolve(base, truth_file) if truth_file else truth_path_for(target_path)
    truth = None
    if truth_path.is_file():
        truth, discrete = _read_truth(truth_path, space, forward, discrete, scale)
    elif truth_file:
        raise ConfigError(f"target.truth = {truth_file!r}: {truth_path} does not exist")
    else:
        truth_path = None

    return FitSetup(
        name=name,
        config_path=config_path,
        target=target,
        target_path=target_path,
        pixel_scale_deg=float(scale),
        forward=forward,
        space=space,
        starts=draw_starts(space, ranges, n_cfg, seed),
        init_ranges=dict(ranges),
        views=views,
        view_options={k: dict(v) for k, v in options.items()},
        solver=solver,
        seed=seed,
        stages=stages,
        scan=scan,
        discrete=tuple(discrete),
        truth=truth,
        truth_path=truth_path,
        out_dir=out,
        model_config=model_config,
        model_path=model_path,
        wavelength_nm=wavelength,
    )
