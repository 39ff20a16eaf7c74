"""Fit configurations: a photo, a model, the free parameters, views and solver settings.

``invglare fit`` and ``invglare sample`` read the same TOML file through
:func:`load_fit`, which checks everything that can be checked before any
solving (keys, paths, bounds, the photo) and returns a :class:`FitSetup`.
Relative paths are relative to the config file.

```toml
[fit]
name = "eye_daylight"            # default: the file's stem
out_dir = "../runs/eye_daylight"  # default: runs/NAME under the current folder

[target]                         # the photo (invglare.config.target)
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
path = "model.aperture.pupil.diameter_mm"    # a parameter path (invglare.config.paths)
lower = 2.0
upper = 4.5
init = 3.3                       # or a range [2.5, 4.0] the starts are drawn from;
                                 # default: the model's value (flux, background: the guess)
prior = "uniform"                # or ["normal", mean, std], ["lognormal", mean_log, std_log]
transform = "auto"               # auto, log, logit, identity
nuisance = false                 # default: true for "obs.*" paths (kept at init in every start)
# A path naming a whole vector leaf (a lash layout's "model.aperture.upper_lashes.layout.
# angle_deg") frees each element with these bounds; indices = [12, 13, 14] picks some.
# Lash angles left without init start from the photo's streaks (invglare.fit.streaks).

[[discrete]]                     # a static choice (integer) tried value by value
path = "model.aperture.diaphragm.n_blades"   # its parameter path, as in [[free]]
values = [5, 6, 7, 8]                # (older configs: key = "model.camera.diaphragm.n_blades")

[views]                          # name = weight: pixels, log, radial, angular, halo
pixels = 1.0

[view_options.angular]           # options of a view (see invglare.fit.views)
n_bins = 72
draws = 32                       # statistics views: weigh by the scatter between 32 eyes
model_draws = 4                  #   (an eye the model did not draw); predict the mean of 4

[[stage]]                        # optional stages run before the final one, in order, each
views = { radial = 1.0, angular = 1.0 }   # from the best result of the one before: e.g.
max_steps = 40                   # draw-independent statistics first, to reach the right
                                 # basin before fitting pixel by pixel ([views], [solver])
fixed = ["obs.dx_px", "obs.dy_px"]  # held at their start values in this stage
branch = { "model.aperture.upper_lashes.count" = [-1, 0, 1] }  # the next stage starts from
                                 # this one's best with the count rounded and moved by each

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
covariance_scale = "auto"        # auto (likelihood: 1, else chi2), chi2, absolute or a number
batch = "vmap"                   # vmap (all starts at once) or loop
```

The tables' readers are in :mod:`invglare.config.fit_tables` and
:mod:`invglare.config.target`; what a fit does with them (staged fits, scans, starts)
is in :mod:`invglare.fit.stages` and :mod:`invglare.fit.starts`.

**Example:**

```python
import jax
from invglare.config.fit import load_fit

with jax.enable_x64(True):               # fits are meant to run in float64
    setup = load_fit("fits/eye_daylight.toml")
    result = setup.fit()                 # the stages, then the final fit
    # one plain fit of the final views:
    # invglare.fit.fit(setup.space, setup.forward, setup.target, setup.views, **setup.fit_kwargs())
```
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import logging
import math
import re
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from invglare._core.memory import check_memory
from invglare.config.fit_tables import (
    DiscreteOption,
    read_discrete,
    read_free,
    read_solver,
    read_stages,
    read_view_options,
    read_views,
)
from invglare.config.paths import get_key, set_key
from invglare.config.section import Section, check_sections
from invglare.config.synth import read_observation, truth_path_for
from invglare.config.target import load_target, read_target_section, read_truth, resolve
from invglare.errors import ConfigError
from invglare.files.outputs import REPORTS_DIR, RUNS_DIR
from invglare.files.toml import load_toml

log = logging.getLogger("invglare")

__all__ = ["SECTIONS", "DiscreteOption", "FitSetup", "load_fit", "read_fit_section"]

if TYPE_CHECKING:
    from invglare.fit.stages import Stage


def __getattr__(name: str) -> Any:
    # `Stage` lives in invglare.fit.stages; imported on first use, as the fit's other
    # modules are here, so that reading this module stays free of JAX.
    if name == "Stage":
        from invglare.fit.stages import Stage

        return Stage
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


#: [sample] belongs to ``invglare sample`` (read by invglare.config.sample); a fit ignores it.
SECTIONS = ("fit", "target", "model", "observation", "free", "discrete", "views", "view_options",
            "stage", "solver", "sample")  # fmt: skip
_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")


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
    - `stages`: the :class:`~invglare.fit.stages.Stage` s run before the final one
      (often none).
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
    - `init_ranges`: ``{column: (low, high)}`` of the parameters whose starts are drawn
      within an init range.
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
        from invglare.fit.starts import draw_starts

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

    def fit(
        self,
        forward: Any = None,
        progress: Callable | None = None,
        *,
        final: bool = True,
        resume: Any = None,
        scan_progress: Callable | None = None,
        stage_done: Callable | None = None,
    ):
        """Run this fit: the scan (if any), the stages, then the final fit.

        A thin call of :func:`invglare.fit.stages.fit_staged` with this setup's photo,
        space, starts, views, stages and solver settings; see there for `final`,
        `resume` and the callbacks (`progress` receives every
        :class:`~invglare.fit.FitProgress`). `forward` defaults to :attr:`forward` (pass
        ``forward_for(choice)`` for a discrete choice). Run it in float64
        (``jax.enable_x64(True)``), as ``invglare fit`` does.

        **Returns:** the :class:`~invglare.fit.FitResult`.

        **Example:**

        ```python
        with jax.enable_x64(True):
            setup = load_fit("fits/eye_daylight.toml")
            result = setup.fit()
        ```
        """
        from invglare.fit.stages import fit_staged

        scan_points = self.draw_starts(self.scan) if self.scan and resume is None else None
        return fit_staged(
            self.space,
            self.forward if forward is None else forward,
            self.target,
            self.views,
            self.starts,
            stages=self.stages,
            scan_points=scan_points,
            view_options=self.view_options,
            truth=self.truth,
            final=final,
            resume=resume,
            progress=progress,
            scan_progress=scan_progress,
            stage_done=stage_done,
            **self.solver,
        )

    def candidates(self) -> list[dict[str, int]]:
        """Every combination of the discrete choices (``[{}]`` when there are none), each
        ``{path: value}``."""
        if not self.discrete:
            return [{}]
        paths = [d.path for d in self.discrete]
        return [
            dict(zip(paths, combo, strict=True))
            for combo in itertools.product(*(d.values for d in self.discrete))
        ]

    def choice(self, stored: Mapping[str, Any]) -> dict[str, int]:
        """A stored discrete choice (``{path or older model-config key: value}``, e.g. from
        a fit's params.json) as ``{path: value}`` of this setup's options; keys of no
        option are refused (:class:`~invglare.errors.ConfigError`)."""
        names = {d.path: d.path for d in self.discrete} | {d.key: d.path for d in self.discrete}
        out = {}
        for name, value in stored.items():
            if name not in names:
                raise ConfigError(
                    f"the discrete choice {name!r} is not one of this fit's "
                    f"({', '.join(d.path for d in self.discrete) or 'none'})"
                )
            out[names[name]] = int(value)
        return out

    def truth_model(self):
        """The model of the ground truth file (as the photo was made), or None without one."""
        if self.truth_path is None:
            return None
        from invglare.config.model import build_model

        model_config, _ = read_truth(self.truth_path)
        return build_model(model_config, self.truth_path.parent, source=str(self.truth_path))

    def forward_for(self, choice: Mapping[str, int]):
        """The forward template with the model rebuilt for one discrete `choice`
        (``{path: value}``; the older model-config keys are accepted too)."""
        from invglare.fit import Forward

        if not choice:
            return self.forward
        keys = {d.path: d.key for d in self.discrete} | {d.key: d.key for d in self.discrete}
        config = copy.deepcopy(self.model_config)
        for name, value in choice.items():
            set_key(config, keys.get(name, name), value)
        model = _build(config, self.model_path, self.target.shape, self.pixel_scale_deg,
                       self.wavelength_nm)  # fmt: skip
        forward = Forward(model, self.forward.obs)
        self.space.check(forward)
        return forward


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


def _truth_values(
    path: Path, space, discrete: list[DiscreteOption], scale_deg: float
) -> tuple[dict[str, float], list[DiscreteOption]]:
    """Truth of each free path, resolved on the forward rebuilt from a ``*.truth.json``,
    and of each discrete choice."""
    from invglare.config.model import build_model
    from invglare.fit import Forward, Observation
    from invglare.fit.paths import read_path

    model_cfg, obs_cfg = read_truth(path)
    truth_model = build_model(model_cfg, path.parent, source=str(path))
    truth_fwd = Forward(truth_model, Observation(**obs_cfg))
    truth = {}
    for p in space.all:
        try:
            value = read_path(truth_fwd, p.path)
        except ConfigError:
            continue  # a parameter the true model does not have: no truth for it
        if p.path == "obs.pixel_scale_ratio":
            # The ratio is model scale / photo scale: the fit's model is built at
            # `scale_deg`, the truth's at its own scale.
            value *= scale_deg / float(truth_model.pixel_scale_deg)
        truth[p.path] = value
    resolved = []
    for d in discrete:
        try:
            value = get_key(model_cfg, d.key, "truth")
        except ConfigError:
            value = None
        resolved.append(dataclasses.replace(d, truth=value if isinstance(value, int) else None))
    return truth, resolved


def read_fit_section(
    config: dict[str, Any], config_path: Path, out_dir: str | Path | None
) -> tuple[str, Path]:
    """The ``[fit]`` table: the fit's name (default the file's stem) and its report folder
    (`out_dir` if given, else ``fit.out_dir`` relative to the config, else runs/NAME)."""
    sec = Section(config.get("fit", {}), "fit")
    name = sec.get("name", str, config_path.stem)
    out_cfg = sec.get("out_dir", str, None)
    sec.finish()
    if not _NAME.match(name):
        raise ConfigError(f"fit.name = {name!r} must be a plain name (letters, digits, _ - .)")
    if out_dir is not None:
        return name, Path(out_dir)
    if out_cfg is not None:
        return name, resolve(config_path.parent, out_cfg)
    return name, RUNS_DIR / name


def stored_fit(setup: FitSetup) -> Path:
    """The fit result a posterior starts from: ``params.json`` in the report folder, else in
    the config's own one (``fit.out_dir`` or ``runs/NAME``), else in the committed
    ``reports/NAME``; the first of them when none exists (the fit then runs there).

    A posterior written elsewhere, or on a fresh clone, thus starts from a stored fit
    instead of running the whole fit again."""
    _, own_dir = read_fit_section(load_toml(setup.config_path), setup.config_path, None)
    folders = dict.fromkeys([setup.out_dir, own_dir, REPORTS_DIR / setup.name])
    for folder in folders:
        if (folder / "params.json").is_file():
            if folder != setup.out_dir:
                log.info("using the stored fit %s", folder / "params.json")
            return folder / "params.json"
    return setup.out_dir / "params.json"


def is_reference_fit(config: dict[str, Any]) -> bool:
    """Whether a parsed fit config fits a reference glare function (``[reference]``, the
    CIE study of :mod:`invglare.cie_study`) rather than a photo."""
    return "reference" in config


def load_fit(
    path: str | Path,
    *,
    out_dir: str | Path | None = None,
    n_starts: int | None = None,
    max_steps: int | None = None,
    config: Mapping[str, Any] | None = None,
) -> FitSetup:
    """Read a fit config, the photo and the model; check them; return a :class:`FitSetup`.

    **Arguments:**

    - `path`: the fit config (TOML, see the module docstring).
    - `out_dir`: override ``fit.out_dir`` (relative to the current folder).
    - `n_starts`, `max_steps`: override the solver settings.
    - `config`: the config's tables, already read (and perhaps edited: ``invglare
      fit-batch`` puts each photo into ``[target]``), used instead of reading `path`;
      relative paths in it are still relative to `path`'s folder.

    The model is built in the current JAX precision: call this inside
    ``jax.enable_x64(True)`` for a float64 fit (as ``invglare fit`` does).

    **Raises:** :class:`~invglare.errors.ConfigError` naming the key for unknown
    tables or keys, a free path that does not exist (listing the valid ones),
    bounds that exclude the initial value, unknown views or options, a model that
    is not monochrome; :class:`~invglare.errors.InputDataError` for a photo that
    cannot be fitted (see :func:`~invglare.config.target.load_target`).
    """
    import equinox as eqx

    from invglare.fit import Forward, Observation, ParameterSpace
    from invglare.fit.starts import draw_starts, photo_guesses
    from invglare.fit.streaks import lash_guesses

    config_path = Path(path)
    config = load_toml(config_path) if config is None else dict(config)
    base = config_path.parent
    check_sections(config, SECTIONS, str(config_path))

    name, out = read_fit_section(config, config_path, out_dir)
    tsec = read_target_section(config, base)
    msec = Section(config.get("model", {}), "model")
    model_file = msec.get("config", str, required=True)
    wavelength = msec.get("wavelength_nm", float, None)
    msec.finish()
    model_path = resolve(base, model_file)
    if not model_path.is_file():
        what = "is a folder, not a TOML file" if model_path.is_dir() else "does not exist"
        raise ConfigError(f"model.config = {model_file!r}: {model_path} {what}")
    model_config = load_toml(model_path)

    target, header_scale = load_target(
        tsec.path,
        channel=tsec.channel,
        linear=tsec.linear,
        saturation=tsec.saturation,
        square=model_config.get("model", {}).get("kind") != "veiling",
    )
    scale = tsec.pixel_scale_deg if tsec.pixel_scale_deg is not None else header_scale
    if scale is None:
        raise ConfigError(
            f"the target photo {tsec.path} has no pixelScaleDeg in its header; set "
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
    obs_fixed["saturation"] = tsec.saturation
    guess = Observation.from_target(target, **obs_fixed)
    forward = Forward(model, guess)

    guesses = photo_guesses(target, guess)
    guesses.update(lash_guesses(target, forward, guesses))  # lash angles from the streaks
    params, nuisance, ranges = read_free(config.get("free"), forward, guesses)
    space = ParameterSpace(params, nuisance)
    space.check(forward)
    discrete = read_discrete(config.get("discrete"), model_config, forward)

    views = read_views(config.get("views", {"pixels": 1.0}), "[views]")
    solver, n_cfg, seed = read_solver(config.get("solver", {}))
    scan = solver.pop("scan")
    stages = read_stages(config.get("stage"), solver["max_steps"], forward, space.paths)
    used = set(views).union(*(st.views for st in stages))
    options = read_view_options(config.get("view_options", {}), used, target.shape, guess, target)

    if n_starts is not None:
        n_cfg = int(n_starts)
    if max_steps is not None:
        solver["max_steps"] = int(max_steps)
        stages = tuple(dataclasses.replace(st, max_steps=int(max_steps)) for st in stages)
    starts_key = "--n-starts" if n_starts is not None else "solver.n_starts"
    if n_cfg < 1:
        raise ConfigError(f"{starts_key}: the number of starts must be >= 1, got {n_cfg}")
    if solver["max_steps"] < 1:
        key = "--max-steps" if max_steps is not None else "solver.max_steps"
        raise ConfigError(f"{key} must be >= 1, got {solver['max_steps']}")
    # The starts are solved side by side: each holds its residuals and their Jacobian.
    check_memory(
        8.0 * n_cfg * target.size * (space.size + 2),
        f"{n_cfg} starts on a {target.shape[1]}x{target.shape[0]} photo with {space.size} "
        f"free parameters ({starts_key} {n_cfg})",
    )

    truth_path = tsec.truth_path or truth_path_for(tsec.path)
    truth = None
    if truth_path.is_file():
        truth, discrete = _truth_values(truth_path, space, discrete, scale)
    elif tsec.truth_path is not None:
        raise ConfigError(f"target.truth = {tsec.truth_file!r}: {truth_path} does not exist")
    else:
        truth_path = None

    starts = draw_starts(space, ranges, n_cfg, seed)
    return FitSetup(
        name=name, config_path=config_path, out_dir=out,
        target=target, target_path=tsec.path, pixel_scale_deg=float(scale),
        truth=truth, truth_path=truth_path,
        model_config=model_config, model_path=model_path, wavelength_nm=wavelength,
        forward=forward, space=space, discrete=tuple(discrete),
        starts=starts, init_ranges=dict(ranges), seed=seed, scan=scan,
        views=views, view_options=options, stages=stages, solver=solver,
    )  # fmt: skip
