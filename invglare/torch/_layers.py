"""Glare layers: a model's PSF and its glare on image batches as ``torch.nn.Module`` s.

Both layers hold an invglare model (an equinox Module, built from a model config or given
built) and a set of *free* parameters chosen by path, exactly as a fit's ``[[free]]``
tables: each has bounds and a transform (:class:`~invglare.fit.Parameter`, ``"auto"``:
logit for two finite bounds, log for a lower bound only). The layer's one
``nn.Parameter``, :attr:`GlarePSF.latent`, holds the **unconstrained latent values** of the
fit's transforms, in the order of :attr:`GlarePSF.paths`: a torch optimiser moves them
freely and the bounds hold by construction. The physical values (mm, degrees, counts) are
:attr:`GlarePSF.physical` (a differentiable tensor) and :meth:`GlarePSF.values` (floats);
:meth:`GlarePSF.set_values` writes physical values.

All computation is invglare's JAX code, reached through :class:`~invglare.torch.JaxFunction`;
gradients flow to the latent parameters and, for :class:`Glare`, to the images.

**Modes.** ``train()`` and ``eval()`` compute the same values (the layers draw nothing at
random). In ``eval()`` mode a :class:`GlarePSF` that needs no gradient (under
``torch.no_grad()``, or with ``latent.requires_grad`` off) keeps its last PSF while its
parameters are unchanged, so an inference loop through :class:`Glare` pays for the
convolution only.

**Precision.** The layers follow their parameters' dtype: ``.to(torch.float64)`` (or
``.double()``) makes every later call float64, the model's arrays cast with it. Building
from a config with ``dtype=torch.float64`` builds the model itself in float64.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import torch
from jaxtyping import Array, Float

from invglare.config.model import build_model
from invglare.errors import ConfigError, InputDataError
from invglare.files.toml import load_toml
from invglare.fit.params import Parameter, ParameterSpace
from invglare.fit.paths import read_path
from invglare.render.billboard import replace_with_billboards
from invglare.render.bright import bright_pixel_list, light_angles_deg, luminance
from invglare.render.convolve import convolve_psf, resample_psf
from invglare.render.ghost_frames import render_ghosts
from invglare.render.position_glare import psf_npix_at_scale
from invglare.torch._bridge import JaxFunction, _precision, to_jax, to_torch

__all__ = ["MODES", "Glare", "GlarePSF", "load_model"]

#: How :class:`Glare` puts glare on an image; ``"auto"`` picks by the model.
MODES = ("auto", "convolve", "billboard", "ghosts")
FREE_KEYS = ("path", "lower", "upper", "init", "transform")
_DTYPES = (torch.float32, torch.float64)


# --------------------------------------------------------------------------------------
# how the model interface says a model is rendered


def _renderer(model: Any) -> str:
    """The :data:`MODES` entry ``"auto"`` resolves to for `model`."""
    if model.centre == "axis":
        return "ghosts"  # a screen image per light (lens ghosts)
    return "convolve" if model.shift_invariant else "billboard"


# --------------------------------------------------------------------------------------
# models and free parameters


def _check_dtype(dtype: torch.dtype | None) -> torch.dtype:
    if dtype is None:
        return torch.float32
    if dtype not in _DTYPES:
        raise ConfigError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
    return dtype


def load_model(
    model: Any, base_dir: str | Path | None = None, *, dtype: torch.dtype | None = None, **grid
) -> eqx.Module:
    """The invglare model of a model config (a TOML path or a dict), or `model` if built.

    **Arguments:**

    - `model`: a path to a model config (``examples/eye_daylight.toml``), its parsed dict,
      or a built model (returned as it is).
    - `base_dir`: folder relative paths in a dict config are read from (a path's own
      folder by default).
    - `dtype`: ``torch.float64`` builds the model in float64 (inside a local
      ``jax.enable_x64`` scope); float32 by default.
    - `grid`: ``npix`` / ``pixel_scale_deg`` / ``wavelengths_nm`` overrides of
      :func:`~invglare.config.model.build_model`.

    **Raises:** :class:`~invglare.errors.ConfigError` for a missing file or a bad config.
    """
    if isinstance(model, str | Path):
        path = Path(model)
        config = load_toml(path)
        with _precision(_check_dtype(dtype) == torch.float64):
            return build_model(config, path.parent if base_dir is None else base_dir,
                               source=str(path), **grid)  # fmt: skip
    if isinstance(model, Mapping):
        with _precision(_check_dtype(dtype) == torch.float64):
            return build_model(dict(model), base_dir, source="model config", **grid)
    if isinstance(model, eqx.Module) and callable(model):
        if grid:
            raise ConfigError(f"grid overrides {sorted(grid)} need a model config, not a model")
        return model
    raise ConfigError(
        "expected a model config (a TOML path or a dict) or a built invglare model, got "
        f"{type(model).__name__}"
    )


def read_free(entries: Sequence[Any], model: Any) -> list[Parameter]:
    """:class:`~invglare.fit.Parameter` s from ``[[free]]``-like entries, checked on `model`.

    An entry is a :class:`~invglare.fit.Parameter`, or a mapping with ``path``, ``lower``,
    ``upper`` and optionally ``init`` (default: the model's value) and ``transform``.
    Paths are relative to the model; a fit's ``"model."`` prefix is accepted and dropped
    (models have no field of that name). A path that does not exist raises a
    :class:`~invglare.errors.ConfigError` listing the valid paths.
    """
    if isinstance(entries, str | Mapping | Parameter):
        entries = [entries]
    params = []
    for i, entry in enumerate(entries):
        if isinstance(entry, Parameter):
            param = entry
        elif isinstance(entry, Mapping):
            unknown = [k for k in entry if k not in FREE_KEYS]
            if unknown:
                raise ConfigError(
                    f"free[{i}]: unknown key {unknown[0]!r}; valid keys: {', '.join(FREE_KEYS)}"
                )
            missing = [k for k in ("path", "lower", "upper") if k not in entry]
            if missing:
                raise ConfigError(f"free[{i}] needs the key {missing[0]!r} (path, lower, upper)")
            path = str(entry["path"])
            path = path[len("model.") :] if path.startswith("model.") else path
            init = entry.get("init")
            init = read_path(model, path) if init is None else init
            param = Parameter(path, entry["lower"], entry["upper"], init=init,
                              transform=entry.get("transform", "auto"))  # fmt: skip
        else:
            raise ConfigError(
                f"free[{i}] must be a Parameter or a table with path, lower, upper; got {entry!r}"
            )
        if param.path.startswith("model."):
            param = dataclasses.replace(param, path=param.path[len("model.") :])
        params.append(param)
    if params:
        ParameterSpace(params).check(model)  # lists the valid paths for one that is missing
    return params


def _is_wide(model: Any) -> bool:
    """True when the model holds float64 arrays (built in float64): trace it in float64."""
    leaves = jax.tree_util.tree_leaves(eqx.filter(model, eqx.is_array))
    return any(x.dtype in (jnp.float64, jnp.complex128) for x in leaves)


def _apply_latent(space: ParameterSpace | None, model: Any, latent: Array) -> Any:
    if space is None:
        return model
    return space.apply(model, space.from_latent_parts([latent[i] for i in range(space.size)]))


def _channels_first(image: Array) -> Array:
    return image[None] if image.ndim == 2 else jnp.moveaxis(image, -1, 0)


# --------------------------------------------------------------------------------------
# the PSF


class GlarePSF(torch.nn.Module):
    """A glare model's image (its PSF) as a tensor, its free parameters trainable.

    **Arguments:**

    - `model`: a model config (TOML path or dict) or a built invglare model (any kind).
    - `free`: the free parameters: ``[[free]]``-like mappings (``path``, ``lower``,
      ``upper``, optional ``init`` and ``transform``) or :class:`~invglare.fit.Parameter` s;
      none for a fixed PSF.
    - `base_dir`: folder for relative paths of a dict config.
    - `pixel_scale_deg`: resample the PSF (energy kept, :func:`~invglare.render.resample_psf`)
      to this many degrees per pixel, e.g. an image's; default: the model's own scale.
    - `max_npix`: the largest side of the resampled PSF (odd; default: its whole field).
    - `dtype`: ``torch.float32`` (default) or ``torch.float64`` (the model is built in it).

    **Output:** ``forward()`` returns ``(C, h, w)`` channels first: ``C = 1`` for a
    monochrome model, 3 for RGB; energy per pixel in the model's normalisation (unit
    energy for PSFs), centred on ``(h // 2, w // 2)``.

    **Parameters:** :attr:`latent` (``nn.Parameter``, shape ``(p,)``) is in the fit's
    *latent* space, one entry per :attr:`paths`; :attr:`physical` gives the physical
    values. ``state_dict()`` holds ``latent`` and the paths (checked on loading).

    **Example:**

    ```python
    psf = GlarePSF("examples/eye_daylight.toml",
                   [{"path": "aperture.pupil.diameter_mm", "lower": 2.0, "upper": 4.5}])
    image = psf()                           # (1, 256, 256), unit energy
    image[0, 128, 128].backward()           # d(peak)/d(latent pupil diameter)
    psf.values()                            # {'aperture.pupil.diameter_mm': 3.0}
    ```
    """

    def __init__(
        self,
        model: Any,
        free: Sequence[Any] = (),
        *,
        base_dir: str | Path | None = None,
        pixel_scale_deg: float | None = None,
        max_npix: int | None = None,
        dtype: torch.dtype | None = None,
    ):
        super().__init__()
        dtype = _check_dtype(dtype)
        self.model = load_model(model, base_dir, dtype=dtype)
        params = read_free(free, self.model)
        self.space = ParameterSpace(params) if params else None
        self.own_scale_deg = float(self.model.pixel_scale_deg)
        self.output_scale_deg = (
            self.own_scale_deg if pixel_scale_deg is None else float(pixel_scale_deg)
        )
        with _precision(_is_wide(self.model)):
            shape = eqx.filter_eval_shape(self.model).shape
        self.channels = 1 if len(shape) == 2 else int(shape[-1])
        self._resample = None
        if pixel_scale_deg is not None and not np.isclose(
            self.output_scale_deg, self.own_scale_deg, rtol=1e-9
        ):
            if not (np.isfinite(self.output_scale_deg) and self.output_scale_deg > 0):
                raise ConfigError(f"pixel_scale_deg must be > 0, got {pixel_scale_deg!r}")
            if self.model.centre == "axis" or shape[0] != shape[1]:
                raise ConfigError(
                    "a veiling model's image is a screen, not a PSF: build it on the image's "
                    "grid (npix, pixel_scale_deg in its config) instead of resampling it"
                )
            limit = int(max_npix) if max_npix is not None else 4 * shape[0] + 1
            npix = psf_npix_at_scale(shape[0], self.own_scale_deg, self.output_scale_deg, limit)
            self._resample = (self.own_scale_deg, self.output_scale_deg, npix)
        with torch.no_grad():
            with _precision(dtype == torch.float64):
                start = self.space.initial_latent() if self.space else jnp.zeros(0)
                # The parameter owns its memory: an optimiser writes it in place, and JAX
                # buffers must never change under JAX.
                latent = to_torch(start).to(dtype).clone()
        self.latent = torch.nn.Parameter(latent)
        self._psf = JaxFunction(
            self._psf_of, consts=self.model, signature=(f"{latent.shape[0]}",),
            names=("latent",), name="GlarePSF",
        )  # fmt: skip
        self._physical = (
            JaxFunction(self.space.from_latent, name="GlarePSF.physical") if self.space else None
        )
        self._cache: tuple | None = None

    # ---- the JAX function

    def _psf_of(self, model: Any, latent: Float[Array, " p"]) -> Float[Array, "c h w"]:
        psf = _apply_latent(self.space, model, latent)()
        if self._resample is not None:
            psf = resample_psf(psf, *self._resample)
        return _channels_first(psf).astype(latent.dtype)

    # ---- parameters

    @property
    def paths(self) -> tuple[str, ...]:
        """The free parameters' paths into the model, in the order of :attr:`latent`."""
        return self.space.paths if self.space else ()

    @property
    def bounds(self) -> dict[str, tuple[float, float]]:
        """``{path: (lower, upper)}`` of the free parameters (physical units)."""
        return {p.path: (p.lower, p.upper) for p in (self.space.all if self.space else ())}

    @property
    def physical(self) -> torch.Tensor:
        """The free parameters' physical values, ``(p,)``, differentiable in :attr:`latent`."""
        if self._physical is None:
            return self.latent * 0
        return self._physical(self.latent)

    def values(self) -> dict[str, float]:
        """``{path: physical value}`` of the free parameters, as floats."""
        with torch.no_grad():
            return dict(zip(self.paths, self.physical.tolist(), strict=True))

    def set_values(self, values: Mapping[str, float] | Sequence[float]) -> None:
        """Write physical values (a ``{path: value}`` mapping or one value per path)."""
        if self.space is None:
            raise ConfigError("this layer has no free parameters to set")
        wide = self.latent.dtype == torch.float64
        with torch.no_grad(), _precision(wide):
            latent = self.space.to_latent(values if isinstance(values, Mapping) else list(values))
            self.latent.copy_(to_torch(latent).to(self.latent.dtype))

    def model_at(self) -> Any:
        """The invglare model with the current physical values (for invglare's own tools)."""
        wide = self.latent.dtype == torch.float64
        with torch.no_grad(), _precision(wide):
            return _apply_latent(self.space, self.model, to_jax(self.latent))

    # ---- state

    def get_extra_state(self) -> dict[str, Any]:
        return {"paths": list(self.paths)}

    def set_extra_state(self, state: Any) -> None:
        paths = list(state.get("paths", [])) if isinstance(state, Mapping) else None
        if paths != list(self.paths):
            raise ConfigError(
                f"the state was saved with the free parameters {paths}, this layer has "
                f"{list(self.paths)}"
            )

    # ---- forward

    def keeps_psf(self) -> bool:
        """True when a call now may reuse the last PSF: ``eval()`` mode and no gradient."""
        return not (self.training or (torch.is_grad_enabled() and self.latent.requires_grad))

    def forward(self) -> torch.Tensor:
        latent = self.latent
        if not self.keeps_psf():
            self._cache = None
            return self._psf(latent)
        key = (latent._version, latent.data_ptr(), latent.dtype)
        if self._cache is not None and self._cache[0] == key:
            out = self._cache[1]
            if out._version == self._cache[2]:  # nobody wrote into the kept PSF
                return out
        out = self._psf(latent.detach())
        self._cache = (key, out, out._version)
        return out

    def extra_repr(self) -> str:
        return (f"{type(self.model).__name__}, free={list(self.paths)}, "
                f"pixel_scale_deg={self.output_scale_deg:g}")  # fmt: skip


# --------------------------------------------------------------------------------------
# glare on images


def _convolve_one(
    image: Float[Array, "c H W"], psf: Float[Array, "k h w"]
) -> Float[Array, "c H W"]:
    out = convolve_psf(jnp.moveaxis(image, 0, -1), jnp.moveaxis(psf, 0, -1))
    return jnp.moveaxis(out, -1, 0).astype(image.dtype)


class Glare(torch.nn.Module):
    """Glare on a batch of linear HDR images ``(B, C, H, W)``, differentiable in both.

    **Arguments:**

    - `model`, `free`, `base_dir`, `dtype`: as for :class:`GlarePSF` (the layer's
      :attr:`psf` submodule holds the parameters: ``state_dict`` key ``psf.latent``).
    - `pixel_scale_deg`: the images' degrees per pixel (default: the model's).
    - `mode`: ``"auto"`` (default) convolves for a shift-invariant model and gives each
      bright pixel its own PSF otherwise (``masking = "position"``; lens ghosts for a
      veiling model); ``"convolve"``, ``"billboard"`` or ``"ghosts"`` force one.
    - `threshold`: bright-pixel luminance for the per-light modes, in the images' units
      (default: 1/100 of each image's brightest luminance).
    - `max_lights`: the per-light modes' number of lights per image (the brightest).
    - `max_psf_npix`: the largest PSF side at the images' scale (default: the PSF's field).

    **Convolution** (``"convolve"``): each image is convolved with the unit-energy PSF
    (:func:`~invglare.render.convolve_psf`, zero-padded: no wrap-around), as
    ``invglare render --mode convolve``: light is spread, not added. **Billboards**
    (``"billboard"``): the `max_lights` brightest pixels above the threshold are replaced
    by the PSF of their own direction (:meth:`KakimotoGlare.batch`, resampled to the images'
    scale), as ``invglare render`` does for ``masking = "position"``. The centre pixel of
    the image is the optical axis. **Ghosts** (``"ghosts"``): the veiling model's ghosts of
    each light (:func:`~invglare.render.ghost_frames.render_ghosts`); the model must be
    built on the images' grid.

    Images are ``(B, 1, H, W)`` or ``(B, 3, H, W)``; an RGB model needs 3 channels, a
    monochrome one is applied to every channel.

    **Example:**

    ```python
    glare = Glare("examples/eye_daylight.toml",
                  [{"path": "aperture.pupil.diameter_mm", "lower": 2.0, "upper": 4.5}],
                  pixel_scale_deg=0.01)
    out = glare(hdr_batch)                  # (B, 3, H, W)
    ```
    """

    def __init__(
        self,
        model: Any,
        free: Sequence[Any] = (),
        *,
        base_dir: str | Path | None = None,
        pixel_scale_deg: float | None = None,
        mode: str = "auto",
        threshold: float | None = None,
        max_lights: int = 16,
        max_psf_npix: int | None = None,
        dtype: torch.dtype | None = None,
    ):
        super().__init__()
        if mode not in MODES:
            raise ConfigError(f"mode {mode!r} is not one of {', '.join(MODES)}")
        self.psf = GlarePSF(model, free, base_dir=base_dir, pixel_scale_deg=pixel_scale_deg,
                            max_npix=max_psf_npix, dtype=dtype)  # fmt: skip
        built = self.psf.model
        auto = _renderer(built)
        self.mode = auto if mode == "auto" else mode
        if self.mode == "convolve" and auto != "convolve":
            raise ConfigError(
                f"a {type(built).__name__} gives each light its own glare (not shift-invariant): "
                f"a convolution cannot render it; use mode = {auto!r}"
            )
        if self.mode == "ghosts" and built.centre != "axis":
            raise ConfigError(
                f"mode 'ghosts' is for models whose image is the screen (veiling), "
                f"not a {type(built).__name__}"
            )
        if self.mode == "billboard" and auto == "ghosts":
            raise ConfigError(f"mode 'billboard' cannot render a {type(built).__name__}")
        if threshold is not None and not (np.isfinite(threshold) and threshold >= 0):
            raise ConfigError(f"threshold must be a number >= 0, got {threshold!r}")
        if int(max_lights) != max_lights or max_lights < 1:
            raise ConfigError(f"max_lights must be an integer >= 1, got {max_lights!r}")
        self.threshold = None if threshold is None else float(threshold)
        self.max_lights = int(max_lights)
        self.pixel_scale_deg = self.psf.output_scale_deg
        self._convolve = JaxFunction(
            _convolve_one, in_axes=(0, None), signature=("B C H W", "K h w"),
            names=("images", "psf"), name="Glare",
        )  # fmt: skip
        p = self.psf.latent.shape[0]
        # PSF and convolution in one compiled call: one DLPack round trip and one autograd
        # node per batch. vmap leaves the PSF unbatched (it does not depend on the image).
        self._psf_convolve = JaxFunction(
            self._psf_convolve_one, consts=built, in_axes=(None, 0),
            signature=(f"{p}", "B C H W"), names=("latent", "images"), name="Glare",
        )  # fmt: skip
        self._per_light = JaxFunction(
            self._render_one, consts=built, in_axes=(None, 0), signature=(f"{p}", "B C H W"),
            names=("latent", "images"), name="Glare",
        )  # fmt: skip

    # ---- rendering (JAX)

    def _psf_convolve_one(self, model: Any, latent: Array, image: Float[Array, "c H W"]) -> Array:
        return _convolve_one(image, self.psf._psf_of(model, latent).astype(image.dtype))

    def _render_one(self, model: Any, latent: Array, image: Float[Array, "c H W"]) -> Array:
        model = _apply_latent(self.psf.space, model, latent)
        img = jnp.moveaxis(image, 0, -1)
        h, w = img.shape[:2]
        if self.threshold is None:
            # The threshold picks the lights; it is no quantity to differentiate.
            level = jax.lax.stop_gradient(jnp.max(luminance(img))) / 100.0
        else:
            level = self.threshold
        bright = bright_pixel_list(img, level, min(self.max_lights, h * w))
        resample = self.psf._resample
        if self.mode == "ghosts":
            out = render_ghosts(model, img, bright, self.pixel_scale_deg)
        elif model.shift_invariant:
            # One PSF for every light: the billboards of the bright pixels alone.
            psf = model() if resample is None else resample_psf(model(), *resample)
            out = replace_with_billboards(img, bright, psf.astype(img.dtype))
        else:
            angles = light_angles_deg(bright, (h, w), self.pixel_scale_deg).astype(img.dtype)
            bank = model.batch(angles)
            if resample is not None:
                bank = jax.vmap(lambda p: resample_psf(p, *resample))(bank)
            out = replace_with_billboards(
                img, bright, bank.astype(img.dtype), psf_index=jnp.arange(bank.shape[0])
            )
        return jnp.moveaxis(out, -1, 0).astype(image.dtype)

    # ---- forward

    def _check_images(self, images: Any) -> None:
        if not isinstance(images, torch.Tensor):
            raise InputDataError(
                f"Glare takes a torch.Tensor of images, got {type(images).__name__}"
            )
        if images.ndim != 4:
            hint = " (one image: images[None])" if images.ndim == 3 else ""
            raise InputDataError(
                f"Glare takes images of shape (B, C, H, W), got {tuple(images.shape)}{hint}"
            )
        c = images.shape[1]
        want = (3,) if self.psf.channels == 3 else (1, 3)
        if c not in want:
            kind = "an RGB" if self.psf.channels == 3 else "a monochrome"
            raise InputDataError(
                f"Glare of {kind} model takes images with "
                f"{' or '.join(str(n) for n in want)} channels (B, C, H, W); got shape "
                f"{tuple(images.shape)}"
            )
        if min(images.shape[2:]) < 1:
            raise InputDataError(f"Glare got empty images of shape {tuple(images.shape)}")

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        self._check_images(images)
        if self.mode == "convolve" and self.psf.keeps_psf():
            # eval() without a gradient: the kept PSF, only the convolution runs.
            psf = self.psf()
            if psf.dtype != images.dtype and images.dtype in _DTYPES:
                psf = psf.to(images.dtype)
            return self._convolve(images, psf)
        latent = self.psf.latent
        if images.dtype in _DTYPES and latent.dtype != images.dtype:
            latent = latent.to(images.dtype)
        if self.mode == "convolve":
            return self._psf_convolve(latent, images)
        return self._per_light(latent, images)

    def extra_repr(self) -> str:
        return f"mode={self.mode!r}, pixel_scale_deg={self.pixel_scale_deg:g}"
