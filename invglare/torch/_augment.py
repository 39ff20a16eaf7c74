"""A glare augmentation for training data: eyes and cameras drawn per sample, glare rendered.

A transform in the style of torchvision's v2 transforms (a callable object on tensors,
no torchvision needed): each call draws one *source* (an eye or a camera model, by
weight), its parameters from ranges given in a config (pupil size, lash count and angle,
particle counts, f-number and blade count, cross-screen angles and spacing, ...), and puts
that glare on the image with :class:`~invglare.torch.Glare` (a convolution, or per-light
PSFs for a ``masking = "position"`` eye).

**Config** (TOML or the same as a dict; relative paths are relative to the file)::

    [augment]
    pixel_scale_deg = 0.02        # the images' degrees per pixel (required)
    probability = 1.0             # chance a sample gets glare; else it passes unchanged
    max_psf_npix = 129            # optional: largest PSF side at the images' scale
    threshold = 100.0             # optional: light threshold of the per-light modes

    [[augment.source]]            # one table per model to draw from
    name = "eye"                  # names the drawn parameters (default "source<i>")
    model = "eye_daylight.toml"   # an invglare model config
    weight = 1.0                  # relative chance of this source (default 1)
    [augment.source.draw]         # path into the model = [low, high], uniform per sample;
    "aperture.pupil.diameter_mm" = [2.0, 4.0]      # or {low, high, integer = true}
    "aperture.upper_lashes.count" = { low = 25, high = 45, integer = true }
    [augment.source.choose]       # a key of the *model config* = the values to pick from
    "model.camera.diaphragm.n_blades" = [5, 6, 8]  # (static: one model built per value)
    [augment.source.set]          # keys of the model config set for this source
    "model.aperture_npix" = 64    # (e.g. a coarser grid than the config's)

**Reproducibility.** Sample `index` of epoch `epoch` draws from
``numpy.random.default_rng([seed, epoch, index])``: the same glare for the same index
whatever the worker, the batch or the order it is loaded in. :class:`GlareDataset` passes
the index; a bare call without one uses a per-process counter (reproducible for a fixed
worker count and sampling order). No global random state is read or changed.

**Workers.** The transform pickles as its config (models and compiled programs are built
again in each worker). JAX is multi-threaded, and a forked child of a process that has
already used it can hang: give the ``DataLoader`` ``multiprocessing_context="spawn"`` (or
``"forkserver"``) when it has workers.
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from invglare.config.section import Section
from invglare.errors import ConfigError, InputDataError, PhysicsRangeError
from invglare.files.toml import load_toml
from invglare.fit.params import Parameter
from invglare.models.raster import AbstractRasterModel
from invglare.torch._layers import Glare

__all__ = ["GlareAugment", "GlareDataset"]


@dataclasses.dataclass(frozen=True)
class _Range:
    path: str
    low: float
    high: float
    integer: bool


@dataclasses.dataclass(frozen=True)
class _Source:
    name: str
    weight: float
    model: dict  # the model config, with the source's fixed `set` keys applied
    base_dir: Path
    draws: tuple[_Range, ...]
    choices: tuple[tuple[str, tuple], ...]


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ConfigError(f"{where} must be a finite number, got {value!r}")
    return float(value)


def _read_range(path: str, value: Any, where: str) -> _Range:
    if isinstance(value, list):
        if len(value) != 2:
            raise ConfigError(f"{where} must be [low, high], got {value!r}")
        low, high, integer = value[0], value[1], False
    elif isinstance(value, dict):
        sec = Section(value, where)
        low = sec.get("low", float, required=True)
        high = sec.get("high", float, required=True)
        integer = sec.get("integer", bool, False)
        sec.finish()
    else:
        raise ConfigError(f"{where} must be [low, high] or {{low, high, integer}}, got {value!r}")
    low, high = _number(low, f"{where} low"), _number(high, f"{where} high")
    if not low < high:
        raise ConfigError(
            f"{where}: low {low:g} must be < high {high:g} (set a fixed value in the model config)"
        )
    if integer and math.floor(high) < math.ceil(low):
        raise ConfigError(f"{where}: no integer lies in [{low:g}, {high:g}]")
    path = path[len("model.") :] if path.startswith("model.") else path
    return _Range(path, low, high, integer)


def _read_source(table: Any, i: int, base: Path) -> _Source:
    where = f"augment.source[{i}]"
    sec = Section(table, where)
    name = sec.get("name", str, f"source{i}")
    model = sec.get("model", (str, dict), required=True)
    weight = _number(sec.get("weight", float, 1.0), f"{where}.weight")
    draw = sec.get("draw", dict, {})
    choose = sec.get("choose", dict, {})
    fixed = sec.get("set", dict, {})
    sec.finish()
    if weight <= 0:
        raise ConfigError(f"{where}.weight must be > 0, got {weight:g}")
    if isinstance(model, str):
        path = base / model
        config, model_base = load_toml(path), path.parent
    else:
        config, model_base = model, base
    for key, value in fixed.items():  # fixed changes of the model config (a smaller grid)
        _config_key(config, key, f"{where}.set")
        config = _with_key(config, key, value)
    draws = tuple(_read_range(p, v, f"{where}.draw.{p!r}") for p, v in draw.items())
    choices = []
    for key, values in choose.items():
        if not isinstance(values, list) or not values:
            raise ConfigError(f"{where}.choose.{key!r} must be a non-empty list, got {values!r}")
        _config_key(config, key, f"{where}.choose")  # the key must exist
        choices.append((key, tuple(values)))
    return _Source(name, weight, config, model_base, draws, tuple(choices))


def _config_key(config: Mapping, key: str, where: str) -> Any:
    node: Any = config
    for part in key.split("."):
        if not isinstance(node, Mapping) or part not in node:
            raise ConfigError(
                f"{where}: {key!r} is no key of the model config (the part {part!r} is "
                f"missing); write a dotted key such as 'model.camera.diaphragm.n_blades'"
            )
        node = node[part]
    return node


def _with_key(config: dict, key: str, value: Any) -> dict:
    out = copy.deepcopy(config)
    node = out
    parts = key.split(".")
    for part in parts[:-1]:
        node = node[part]
    node[parts[-1]] = value
    return out


def _check_window(layer: Glare, source: _Source, choice: tuple) -> None:
    """Refuse ranges whose extremes put the aperture outside the model's raster window.

    Values written into a built model are not checked by its constructor, and an opening
    wider than the window would be cut off silently; the extremes of every range (all low,
    all high) are checked instead, which covers openings that grow or shrink with a value.
    """
    space, model = layer.psf.space, layer.psf.model
    aperture = getattr(model, "aperture", None)
    if not isinstance(model, AbstractRasterModel) or not hasattr(aperture, "extent_mm"):
        return  # no raster window to leave
    width = float(model.propagator.grid.width_mm)
    for end in ("low", "high"):
        values = [getattr(r, end) for r in source.draws]
        extent = float(space.apply(model, values).aperture.extent_mm())
        if extent > width * (1 + 1e-6):
            raise PhysicsRangeError(
                f"augment source {source.name!r}{' ' + str(choice) if choice else ''}: with every "
                f"range at its {end} end the aperture is {extent:g} mm across, wider than the "
                f"model's window ({width:g} mm); narrow the ranges or widen model.window_mm"
            )


class GlareAugment:
    """Glare drawn per sample from a config of eye and camera parameter ranges.

    **Arguments:**

    - `config`: the config (see the module): a TOML path, or a dict holding ``augment``.
    - `seed`: the seed of every draw.
    - `base_dir`: folder for the relative model paths of a dict config.
    - `return_clean`, `return_params`: return a dict instead of the glared image alone:
      ``{"glared": ..., "clean": ..., "params": ...}`` with the keys asked for. `clean` is
      the input image; `params` is ``{"source": index, "<name>/<path>": value, ...}`` as
      0-d tensors, one key for every drawn value of every source (NaN for those of the
      sources not drawn, so that a ``DataLoader`` can stack them; ``source`` is -1 for a
      sample left clean).

    **Call:** ``augment(image, index=None)`` with `image` ``(C, H, W)`` or ``(B, C, H, W)``
    linear HDR values (float32 or float64; a batch draws sample ``index + b`` for its
    ``b``-th image). Rendering needs no gradient and runs under ``torch.no_grad``.

    **Example:**

    ```python
    augment = GlareAugment("examples/torch_augment.toml", seed=0, return_clean=True)
    sample = augment(hdr_image, index=7)    # {"glared": ..., "clean": hdr_image}
    ```
    """

    def __init__(
        self,
        config: str | Path | Mapping[str, Any],
        *,
        seed: int = 0,
        base_dir: str | Path | None = None,
        return_clean: bool = False,
        return_params: bool = False,
    ):
        if isinstance(config, str | Path):
            base = Path(config).parent
            config = load_toml(config)
        else:
            base = Path(base_dir) if base_dir is not None else Path.cwd()
        if not isinstance(config, Mapping) or set(config) != {"augment"}:
            keys = sorted(config) if isinstance(config, Mapping) else config
            raise ConfigError(f"an augmentation config holds one [augment] table, got {keys!r}")
        if int(seed) != seed:
            raise ConfigError(f"seed must be an integer, got {seed!r}")
        self._init = (dict(config), int(seed), base, bool(return_clean), bool(return_params))
        self._setup(*self._init)

    def _setup(self, config, seed, base, return_clean, return_params) -> None:
        sec = Section(config["augment"], "augment")
        self.pixel_scale_deg = _number(
            sec.get("pixel_scale_deg", float, required=True), "augment.pixel_scale_deg"
        )
        self.probability = _number(sec.get("probability", float, 1.0), "augment.probability")
        self.max_psf_npix = sec.get("max_psf_npix", int, None)
        self.threshold = sec.get("threshold", float, None)
        tables = sec.get("source", list, required=True)
        sec.finish()
        if not self.pixel_scale_deg > 0:
            raise ConfigError(f"augment.pixel_scale_deg must be > 0, got {self.pixel_scale_deg}")
        if not 0.0 <= self.probability <= 1.0:
            raise ConfigError(f"augment.probability must lie in [0, 1], got {self.probability}")
        if not tables:
            raise ConfigError("augment.source is empty: give at least one [[augment.source]]")
        self.sources = tuple(_read_source(t, i, base) for i, t in enumerate(tables))
        names = [s.name for s in self.sources]
        if len(set(names)) != len(names):
            raise ConfigError(f"augment.source names must differ, got {names}")
        self.seed, self.return_clean, self.return_params = seed, return_clean, return_params
        self.epoch = 0
        self._calls = itertools.count()
        self._layers: dict[tuple, Glare] = {}
        weights = np.asarray([s.weight for s in self.sources])
        self._weights = weights / weights.sum()
        #: Every key of a sample's parameters, in a fixed order.
        self.param_keys = ("source", *(
            f"{s.name}/{k}" for s in self.sources
            for k in (*(r.path for r in s.draws), *(c[0] for c in s.choices))
        ))  # fmt: skip
        for i in range(len(self.sources)):
            # Build the first model of each source now: a bad path fails here, not mid-epoch.
            self._layer(i, tuple(values[0] for _, values in self.sources[i].choices))

    # ---- pickling: the config travels, built models do not

    def __getstate__(self) -> dict[str, Any]:
        return {"init": self._init, "epoch": self.epoch}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self._init = state["init"]
        self._setup(*self._init)
        self.epoch = state["epoch"]

    # ---- draws

    def set_epoch(self, epoch: int) -> None:
        """Draw other glare for the same indices from now on (call once per epoch)."""
        self.epoch = int(epoch)

    def draw(self, index: int) -> dict[str, Any]:
        """The parameters of sample `index`: ``{"source", "choice", "values", "glare"}``."""
        rng = np.random.default_rng([self.seed, self.epoch, int(index)])
        glare = bool(rng.random() < self.probability)
        i = int(rng.choice(len(self.sources), p=self._weights))
        source = self.sources[i]
        choice = tuple(values[int(rng.integers(len(values)))] for _, values in source.choices)
        values = []
        for r in source.draws:
            if r.integer:
                values.append(float(rng.integers(math.ceil(r.low), math.floor(r.high) + 1)))
            else:
                values.append(float(rng.uniform(r.low, r.high)))
        return {"source": i, "choice": choice, "values": tuple(values), "glare": glare}

    def _layer(self, i: int, choice: tuple) -> Glare:
        key = (i, choice)
        if key not in self._layers:
            source = self.sources[i]
            config = source.model
            for (k, _), value in zip(source.choices, choice, strict=True):
                config = _with_key(config, k, value)
            free = [
                Parameter(r.path, r.low, r.high, init=r.low, transform="identity")
                for r in source.draws
            ]
            layer = Glare(
                config, free, base_dir=source.base_dir, pixel_scale_deg=self.pixel_scale_deg,
                threshold=self.threshold, max_psf_npix=self.max_psf_npix,
            )  # fmt: skip
            if free:
                _check_window(layer, source, choice)
            self._layers[key] = layer.eval()
        return self._layers[key]

    def _params(self, drawn: dict[str, Any] | None) -> dict[str, torch.Tensor]:
        out = dict.fromkeys(self.param_keys, math.nan)
        out["source"] = -1
        if drawn is not None and drawn["glare"]:
            source = self.sources[drawn["source"]]
            out["source"] = drawn["source"]
            for r, v in zip(source.draws, drawn["values"], strict=True):
                out[f"{source.name}/{r.path}"] = v
            for (k, _), v in zip(source.choices, drawn["choice"], strict=True):
                out[f"{source.name}/{k}"] = float(v)
        return {k: torch.tensor(v) for k, v in out.items()}

    # ---- rendering

    def render(self, image: torch.Tensor, drawn: dict[str, Any]) -> torch.Tensor:
        """`image` ``(C, H, W)`` with the glare of the draw `drawn` (see :meth:`draw`)."""
        if not drawn["glare"]:
            return image.clone()
        layer = self._layer(drawn["source"], drawn["choice"])
        with torch.no_grad():
            if layer.psf.latent.numel():
                values = torch.tensor(drawn["values"], dtype=layer.psf.latent.dtype)
                layer.psf.latent.copy_(values)  # identity transforms: latent = physical
            return layer(image[None])[0]

    def __call__(self, image: torch.Tensor, index: int | None = None):
        if not isinstance(image, torch.Tensor) or image.ndim not in (3, 4):
            shape = tuple(image.shape) if isinstance(image, torch.Tensor) else type(image).__name__
            raise InputDataError(
                f"GlareAugment takes an image (C, H, W) or a batch (B, C, H, W), got {shape}"
            )
        batched = image.ndim == 4
        images = image if batched else image[None]
        if index is None:
            worker = torch.utils.data.get_worker_info()
            # A stream per worker: reproducible for a fixed worker count and order.
            start = (next(self._calls) * 1000003 + (worker.id if worker else 0)) * len(images)
        else:
            start = int(index)
        draws = [self.draw(start + b) for b in range(len(images))]
        glared = torch.stack([self.render(img, d) for img, d in zip(images, draws, strict=True)])
        glared = glared if batched else glared[0]
        if not (self.return_clean or self.return_params):
            return glared
        out = {"glared": glared}
        if self.return_clean:
            out["clean"] = image
        if self.return_params:
            per = [self._params(d) for d in draws]
            params = {k: torch.stack([p[k] for p in per]) for k in self.param_keys}
            out["params"] = params if batched else {k: v[0] for k, v in params.items()}
        return out

    def __repr__(self) -> str:
        names = ", ".join(s.name for s in self.sources)
        return f"GlareAugment(sources=[{names}], seed={self.seed}, epoch={self.epoch})"


class GlareDataset(torch.utils.data.Dataset):
    """A dataset of images with glare drawn per index (reproducible in any worker).

    **Arguments:**

    - `images`: a ``(N, C, H, W)`` tensor or any dataset whose items are ``(C, H, W)``
      tensors (or tuples whose first element is one).
    - `augment`: the :class:`GlareAugment`.

    Item `i` is ``augment(images[i], index=i)``.

    **Example:**

    ```python
    data = GlareDataset(hdr_images, GlareAugment(config, return_clean=True))
    loader = DataLoader(data, batch_size=8, num_workers=2, multiprocessing_context="spawn")
    ```
    """

    def __init__(self, images: Any, augment: GlareAugment):
        if not isinstance(augment, GlareAugment):
            raise ConfigError(f"augment must be a GlareAugment, got {type(augment).__name__}")
        self.images = images
        self.augment = augment

    def __len__(self) -> int:
        return len(self.images)

    def __getitem__(self, index: int):
        item = self.images[index]
        image = item[0] if isinstance(item, tuple | list) else item
        return self.augment(image, index=index)
