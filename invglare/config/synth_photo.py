"""Synthetic photos with their ground truth: what ``invglare synth`` draws and writes.

For a spec (:mod:`invglare.config.synth`) the model's PSF is computed in float64, turned
into mean counts by the observation and a noisy photo drawn with the spec's seed
(:func:`synthesize`); :func:`write_synth` writes ``NAME.exr`` and ``NAME.truth.json``
atomically. Here, below the commands, so that the benchmarks can draw photos too.
"""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from invglare.config.synth import OBSERVATION_KEYS, SynthSpec
from invglare.errors import ConfigError, InvglareError, prefixed

TRUTH_FORMAT = "invglare.synth"
TRUTH_VERSION = 1
#: Largest rounding error of a half-float pixel allowed, in units of that pixel's noise.
HALF_MAX_ERROR_SIGMA = 0.2
_HALF_MAX = float(np.finfo(np.float16).max)


def observation_table(obs) -> dict[str, Any]:
    """Every field of an :class:`~invglare.fit.Observation` as plain numbers (None where unset)."""
    out: dict[str, Any] = {}
    for name in OBSERVATION_KEYS:
        value = getattr(obs, name)
        out[name] = None if value is None else float(value)
    return out


def build_truth_forward(spec: SynthSpec):
    """The spec's ``Forward(model, observation)`` (call inside ``jax.enable_x64(True)``)."""
    import jax.numpy as jnp

    from invglare.config.model import build_model
    from invglare.fit import Forward, Observation, Parameter, ParameterSpace

    model = build_model(spec.model_config, spec.base_dir, source=str(spec.model_path or spec.path))
    try:
        obs = Observation(**spec.observation)
    except InvglareError as err:  # name the table the bad value came from
        raise type(err)(f"{spec.path} [observation]: {err}") from err
    forward = Forward(model, obs)
    if spec.set_values:
        # One Parameter per [set] entry only to resolve and write its path (unknown
        # paths list the valid ones); the bounds are irrelevant here.
        params = [Parameter(p, -math.inf, math.inf, init=v) for p, v in spec.set_values.items()]
        space = ParameterSpace(params)
        space.check(forward)
        forward = space.apply(forward, jnp.asarray(list(spec.set_values.values())))
        # Values written by path skip the readers' range checks: read the result back.
        with prefixed(f"{spec.path} [set]"):
            build_model(forward.model.to_config(), spec.base_dir, source=str(spec.path))
    return forward


@functools.cache
def _draw():
    """The jitted draw of a noisy photo and its mean counts: made once, so that the members
    of a population (one structure) share one compiled program."""
    import equinox as eqx

    def draw(fwd, key):
        psf = fwd.model()
        return fwd.obs.sample(key, psf), fwd.obs.expected(psf)

    return eqx.filter_jit(draw)


def synthesize(spec: SynthSpec) -> tuple[np.ndarray, dict[str, Any]]:
    """Draw the spec's photo. **Returns:** ``(photo as stored, truth dict)``; nothing is written."""
    import equinox as eqx
    import jax

    with jax.enable_x64(True):
        forward = build_truth_forward(spec)
        shape = eqx.filter_eval_shape(forward.model).shape
        if len(shape) != 2:
            raise ConfigError(
                f"{spec.path}: the model gives a PSF of shape {shape}; a synthetic photo needs a "
                "monochrome model: set [spectrum] wavelengths_nm to one value"
            )
        photo, expected = _draw()(forward, jax.random.key(spec.seed))
        photo = np.asarray(photo, dtype=np.float64)
        expected = np.asarray(expected, dtype=np.float64)
        variance = np.asarray(forward.obs.variance(expected))
        obs = forward.obs
        model_config = forward.model.to_config()
        model_scale = float(forward.model.pixel_scale_deg)
        wavelengths = forward.model.wavelengths_nm

    if not np.all(np.isfinite(photo)):
        raise ConfigError(f"{spec.path}: the synthetic photo has non-finite pixels")
    if spec.pixel_type == "half":
        if photo.max() > _HALF_MAX or photo.min() < -_HALF_MAX:
            raise ConfigError(
                f"{spec.path}: pixel values reach {np.abs(photo).max():.6g} counts, beyond the "
                f"largest half float {_HALF_MAX:g}; lower the flux, set a saturation level, or "
                "use synth.pixel_type = 'float'"
            )
        stored = photo.astype(np.float16)
        error = np.abs(stored.astype(np.float64) - photo) / np.sqrt(variance + 1e-30)
        if error.max() > HALF_MAX_ERROR_SIGMA:
            raise ConfigError(
                f"{spec.path}: half floats would round a pixel by {error.max():.3g} times its "
                f"noise (at most {HALF_MAX_ERROR_SIGMA} allowed); use synth.pixel_type = 'float'"
            )
        photo = stored.astype(np.float64)
    else:
        photo = photo.astype(np.float32).astype(np.float64)

    ratio = float(obs.pixel_scale_ratio)
    saturated = 0 if obs.saturation is None else int(np.sum(photo >= obs.saturation))
    truth = {
        "format": TRUTH_FORMAT,
        "version": TRUTH_VERSION,
        "photo": spec.out_exr.name,
        "spec": spec.path.name,
        "shape": list(photo.shape),
        # The photo's scale: the model's, divided by the magnification pixel_scale_ratio.
        "pixel_scale_deg": model_scale / ratio,
        "wavelengths_nm": wavelengths,
        "noise_seed": spec.seed,
        "pixel_type": spec.pixel_type,
        "model": model_config,
        "observation": observation_table(obs),
        "set": dict(spec.set_values),
        "stats": {
            "max_counts": float(photo.max()),
            "sum_counts": float(photo.sum()),
            "saturated_pixels": saturated,
            "peak_expected_counts": float(expected.max()),
        },
    }
    if spec.drawn:
        truth["drawn"] = dict(spec.drawn)
    return photo, truth


def write_synth(spec: SynthSpec, photo: np.ndarray, truth: dict[str, Any]) -> tuple[Path, Path]:
    """Write ``NAME.exr`` and ``NAME.truth.json`` atomically. **Returns:** both paths."""
    from invglare.files.atomic import write_json_atomic
    from invglare.files.exr import write_exr

    attrs = {
        "invglareObservation": json.dumps(truth["observation"], sort_keys=True),
        "invglareNoiseSeed": int(spec.seed),
        "invglareUnits": "counts",
    }
    exr = write_exr(
        spec.out_exr,
        photo.astype(np.float32),
        pixel_scale_deg=truth["pixel_scale_deg"],
        wavelengths_nm=truth["wavelengths_nm"],
        config=truth["model"],
        attrs=attrs,
        half=spec.pixel_type == "half",
    )
    truth_file = write_json_atomic(spec.out_truth, truth)
    return exr, truth_file
