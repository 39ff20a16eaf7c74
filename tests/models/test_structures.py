"""Structures against the raster (issue 27, item 2): aliased gratings refused, the first
lenticular order of a resolved grating at lambda / spacing, unresolved structures warned of."""

import math
import warnings

import numpy as np
import pytest

from invglare.aperture.eye import EyeAperture, Gratings, Particles, Pupil
from invglare.dynamics import EyeDynamics
from invglare.errors import PhysicsRangeError, RasterWarning
from invglare.models.kakimoto import KakimotoGlare
from invglare.models.structures import structures_of
from invglare.models.temporal import TemporalGlare


def grating_eye(spacing_mm: float, thickness_mm: float, count: float = 60.0) -> EyeAperture:
    """A clear 6 mm pupil behind many patches of radial lens-fibre lines."""
    return EyeAperture(
        pupil=Pupil(6.0),
        gratings=Gratings(
            count=count,
            n_max=math.ceil(count),
            key=3,
            spacing_mm=spacing_mm,
            line_thickness_mm=thickness_mm,
            line_length_mm=1.2,
            inner_radius_mm=0.8,
            outer_radius_mm=2.6,
            lines_per_grating=9,
        ),
    )


def test_a_grating_below_nyquist_is_refused_naming_the_raster_it_needs():
    """40 um lines on a 49 um raster would alias; the message says aperture_npix >= 316."""
    eye = grating_eye(0.04, 0.012)
    for build in (
        lambda: KakimotoGlare.build(
            eye,
            focal_length_mm=17.0,
            obstacle_distance_mm=0.0,
            aperture_npix=128,
            window_mm=6.3,
            npix=128,
            wavelengths_nm=550.0,
            colour="spectral",
        ),
        lambda: TemporalGlare.build(eye, EyeDynamics.frozen(), aperture_npix=128, npix=256),
    ):
        with pytest.raises(PhysicsRangeError, match=r"aliases.*aperture_npix >= \d+"):
            build()


def test_the_first_lenticular_order_of_a_resolved_grating_is_at_lambda_over_spacing():
    """0.25 mm gratings (5 px) at 550 nm: the halo ring peaks at 0.126 deg, within a pixel."""
    spacing, lam = 0.25, 550.0
    eye = grating_eye(spacing, 0.1)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RasterWarning)  # resolved and inside the field
        model = KakimotoGlare.build(
            eye,
            focal_length_mm=17.0,
            obstacle_distance_mm=0.0,
            aperture_npix=128,
            window_mm=6.4,
            npix=128,
            pixel_scale_deg=0.004,
            wavelengths_nm=lam,
            colour="spectral",
        )
    psf = np.asarray(model(), np.float64)
    yy, xx = np.mgrid[:128, :128] - 64
    r = np.hypot(yy, xx)
    bins = np.round(r).astype(int)
    profile = np.bincount(bins.ravel(), psf.ravel()) / np.bincount(bins.ravel())
    expected_px = math.degrees(lam * 1e-6 / spacing) / 0.004  # 31.5 px
    window = np.arange(int(expected_px) - 10, int(expected_px) + 11)
    peak = window[np.argmax(profile[window])]
    assert abs(peak - expected_px) <= 1.0, (peak, expected_px)
    # a real ring: its peak stands above the diffraction of the pupil around it
    assert profile[peak] > 3.0 * profile[peak - 8] and profile[peak] > 3.0 * profile[peak + 8]


def test_unresolved_structures_and_orders_beyond_the_field_are_warned_of():
    eye = EyeAperture(
        pupil=Pupil(4.0),
        particles=(Particles(count=10.0, n_max=10, key=1, region="cornea", radius_mean_mm=0.0075),),
    )
    names = [s.name for s in structures_of(eye)]
    assert names == ["cornea particles (2 x radius_mean_mm)"]
    with pytest.warns(RasterWarning, match=r"cornea particles.*aperture_npix >= 280"):
        KakimotoGlare.build(
            eye,
            focal_length_mm=17.0,
            obstacle_distance_mm=0.0,
            aperture_npix=64,
            window_mm=4.2,
            npix=64,
            wavelengths_nm=550.0,
            colour="spectral",
        )
    # A resolved 0.1 mm grating: its first order (0.44 deg at 770 nm) beyond a 0.26 deg field.
    with pytest.warns(RasterWarning, match="first order reaches 0.441 deg"):
        KakimotoGlare.build(
            grating_eye(0.1, 0.05),
            focal_length_mm=17.0,
            obstacle_distance_mm=0.0,
            aperture_npix=128,
            window_mm=6.4,
            npix=128,
            pixel_scale_deg=0.004,
            wavelengths_nm=[450.0, 550.0, 770.0],
            colour="paper_rgb",
        )
