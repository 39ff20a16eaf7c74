"""The temporal eye's frames by progressive quads (invglare.models.quad_sequence)."""

from __future__ import annotations

import numpy as np
import pytest
from test_temporal import NPIX, effective, moving_dynamics, small_eye

from invglare.aperture.eye import EyeAperture, Pupil
from invglare.errors import PhysicsRangeError
from invglare.models.quad_sequence import progressive_psf_sequence
from invglare.models.temporal import TemporalGlare
from invglare.optics.quad import ProgressiveQuads


@pytest.mark.slow
def test_progressive_frames_of_the_temporal_eye():
    """A blinking, hippus-driven small eye over 12 frames (through a closed blink): the
    progressive frames have the model's shape, carry its spectral copies, agree with a
    from-scratch quad evaluation of each frame's aperture, and with the model's own
    chirp-sampled FFT frames where the eye is open to the sampling of this 64 px raster
    (measured 7 % of each frame's peak: the FFT samples the Fresnel term at pixel centres,
    the quads integrate it; nearly closed, a few pixels open, 12-50 %)."""
    model = effective(small_eye(), moving_dynamics(), npix=NPIX, key=11)
    psfs, stats = progressive_psf_sequence(model, 12)
    _, ref = model.psf_sequence(12)
    ref = np.asarray(ref)
    assert psfs.shape == ref.shape == (12, NPIX, NPIX, 3)
    assert stats[0].full and not any(s.full for s in stats[1:])
    _, apertures = model.aperture_sequence(12)
    power = np.sum(np.asarray(apertures) ** 2, axis=(1, 2))
    for k in np.flatnonzero(power > 0.5 * power.max()):
        assert np.max(np.abs(psfs[k] - ref[k])) < 0.1 * ref[k].max()
    closed = [k for k in range(12) if ref[k].max() == 0]
    assert closed and all(np.all(psfs[k] == 0) for k in closed)


@pytest.mark.slow
def test_progressive_mono_frames_equal_fresh_quad_evaluations():
    """Pupil only, monochrome: each progressive frame is its aperture's quad near field at
    the model's effective Fresnel distance; at the retina's 17 mm float32 is refused."""
    eye = EyeAperture(pupil=Pupil(5.0))
    kw = dict(npix=32, key=3, wavelengths_nm=575.0)
    with pytest.raises(PhysicsRangeError, match="float64"):
        progressive_psf_sequence(TemporalGlare.build(eye, moving_dynamics(), **kw), 2)
    model = effective(eye, moving_dynamics(), **kw)
    psfs, _ = progressive_psf_sequence(model, 6)
    _, apertures = model.aperture_sequence(6)
    prop = model.propagator
    fresh = ProgressiveQuads(prop.grid, prop.output, 575.0, model.fresnel_distance_mm)
    for k, aperture in enumerate(np.asarray(apertures)):
        ref = fresh.full_psf(aperture)
        assert np.max(np.abs(psfs[k] - ref)) <= 1e-5 * max(ref.max(), 1e-30)
