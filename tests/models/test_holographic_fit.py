"""Recovering focus and pupil from a synthetic defocused glare photo of the holographic eye.

The fit machinery is generic over models addressed by path: ``Forward(model, obs)`` with
the model's speckle-free PSF (:meth:`HolographicEye.__call__`) and the parameters
``model.accommodation_d`` (the lens's focus, D) and ``model.eye.pupil.diameter_mm``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import x64

from invglare.aperture.eye import EyeAperture, Pupil
from invglare.fit import Forward, Observation, Parameter, ParameterSpace, fit
from invglare.models.holographic import HolographicEye

TRUE_PUPIL_MM = 3.0
TRUE_FOCUS_MM = 1600.0  # the source is at 1 m: 0.375 D of defocus, 0.77 waves at the edge
SOURCE_MM = 1000.0


@pytest.mark.slow
def test_fit_recovers_focus_distance_and_pupil_diameter_from_a_defocused_photo():
    with x64():
        truth_model = HolographicEye.build(
            EyeAperture(pupil=Pupil(TRUE_PUPIL_MM)), npix=96, window_mm=8.0,
            wavelengths_nm=(550.0,), focus_distance_mm=TRUE_FOCUS_MM, depth_mm=SOURCE_MM,
            layers=("pupil", "lens"), max_pupil_mm=4.0,
        )  # fmt: skip
        obs = Observation(flux=2e6, background=20.0, gain=1.0, read_noise=3.0)
        expected = np.asarray(Forward(truth_model, obs).expected())
        rng = np.random.default_rng(11)
        photo = rng.poisson(expected) + rng.normal(0.0, 3.0, expected.shape)
        # Start from a wrong eye: a 2.5 mm pupil focused at 5 m. The focus is bounded to lie
        # beyond the source (A < 1 D): defocus of either sign blurs a round pupil alike.
        start = HolographicEye.build(
            EyeAperture(pupil=Pupil(2.5)), npix=96, window_mm=8.0, wavelengths_nm=(550.0,),
            focus_distance_mm=5000.0, depth_mm=SOURCE_MM, layers=("pupil", "lens"),
            max_pupil_mm=4.0,
        )  # fmt: skip
        space = ParameterSpace(
            [
                Parameter("model.eye.pupil.diameter_mm", 2.0, 4.0, init=2.5),
                Parameter("model.accommodation_d", 0.0, 0.95, init=0.2),
            ],
            nuisance=[Parameter("obs.flux", 0.0, float("inf"), init=1.5e6)],
        )
        result = fit(
            space,
            Forward(start, obs),
            jnp.asarray(photo),
            {"pixels": 1.0},
            n_starts=2,
            key=jax.random.key(0),
            max_steps=128,
            truth={
                "model.eye.pupil.diameter_mm": TRUE_PUPIL_MM,
                "model.accommodation_d": 1000.0 / TRUE_FOCUS_MM,
            },
        )
    values = result.values
    pupil = values["model.eye.pupil.diameter_mm"]
    acc = values["model.accommodation_d"]
    assert pupil == pytest.approx(TRUE_PUPIL_MM, rel=0.01), values
    assert acc == pytest.approx(1000.0 / TRUE_FOCUS_MM, abs=0.01), values
    assert 1000.0 / acc == pytest.approx(TRUE_FOCUS_MM, rel=0.03)
