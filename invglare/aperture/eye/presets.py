"""Two ready-made eyes: :func:`daylight_eye` and :func:`night_eye`."""

from __future__ import annotations

import jax
from jaxtyping import Array, Key

from invglare._core.checks import as_key
from invglare.aperture.eye.aperture import EyeAperture
from invglare.aperture.eye.inclusions import Gratings, Particles
from invglare.aperture.eye.lashes import Eyelashes
from invglare.aperture.eye.pupil import Eyelids, Pupil
from invglare.aperture.eye.schema import SEED_TAGS


def _preset_key(key, tag: int) -> Key[Array, ""]:
    return jax.random.fold_in(as_key(key), tag)


def daylight_eye(key: Key[Array, ""] | int = 0) -> EyeAperture:
    """A bright-light eye: small pupil, slightly narrowed lids, lashes, a few cornea cells.

    - pupil: 3.0 mm, round, centred;
    - lids: upper opening 2.2 mm, lower 3.0 mm (a mild squint), no tilt, curvature
      0.04 /mm;
    - upper lashes: 40 (pool 48), length 2.5 mm, thickness 0.06 mm, spread 12 deg,
      jitter 0.5, curvature 0.05 /mm, span 8 mm;
    - lower lashes: 20 (pool 24), length 2.0 mm, thickness 0.05 mm, spread 15 deg,
      jitter 0.5, curvature -0.05 /mm, span 7 mm;
    - particles: 60 cornea cells (pool 64), radius 7.5 um (15 um cells), spread 0.2,
      over a disk of 5.5 mm.

    No gratings: the 1.5 mm pupil radius lies inside the lens cortex's annulus.
    `key` seeds every component (``fold_in(key, tag)``, as :func:`eye_from_config`).
    """
    return EyeAperture(
        pupil=Pupil(3.0),
        lids=Eyelids(2.2, 3.0, 0.0, 0.0, 0.04),
        upper_lashes=Eyelashes(
            count=40.0,
            n_max=48,
            key=_preset_key(key, SEED_TAGS["lashes_upper"]),
            lid="upper",
            angular_spread_deg=12.0,
            thickness_mm=0.06,
            length_mm=2.5,
            curvature_per_mm=0.05,
            root_span_mm=8.0,
        ),
        lower_lashes=Eyelashes(
            count=20.0,
            n_max=24,
            key=_preset_key(key, SEED_TAGS["lashes_lower"]),
            lid="lower",
            angular_spread_deg=15.0,
            thickness_mm=0.05,
            length_mm=2.0,
            curvature_per_mm=-0.05,
            root_span_mm=7.0,
        ),
        particles=(
            Particles(
                count=60.0,
                n_max=64,
                key=_preset_key(key, SEED_TAGS["particles"]),
                region="cornea",
                radius_mean_mm=0.0075,
                radius_spread=0.2,
                region_radius_mm=5.5,
            ),
        ),
    )


def night_eye(key: Key[Array, ""] | int = 0) -> EyeAperture:
    """A dark-adapted eye: wide pupil, open lids, lens and vitreous particles, gratings.

    - pupil: 7.0 mm, round, centred;
    - lids: upper opening 4.5 mm, lower 4.0 mm, no tilt, curvature 0.04 /mm;
    - upper lashes: 80 (pool 96), length 3.0 mm, thickness 0.08 mm, spread 10 deg,
      jitter 0.5, curvature 0.05 /mm, span 9 mm;
    - lens nucleus: 750 particles (Ritschel et al.'s count), radius 10 um, spread 0.3,
      ball of 2.5 mm;
    - vitreous: 250 particles, radius 20 um, spread 0.3, ball of 6 mm;
    - gratings: 200 (Ritschel et al.'s count), 5 lines each, spacing 40 um, width
      12 um, length 0.3 mm, annulus 2.0-3.5 mm.

    `key` seeds every component (``fold_in(key, tag)``, as :func:`eye_from_config`).
    """
    return EyeAperture(
        pupil=Pupil(7.0),
        lids=Eyelids(4.5, 4.0, 0.0, 0.0, 0.04),
        upper_lashes=Eyelashes(
            count=80.0,
            n_max=96,
            key=_preset_key(key, SEED_TAGS["lashes_upper"]),
            lid="upper",
            angular_spread_deg=10.0,
            thickness_mm=0.08,
            length_mm=3.0,
            curvature_per_mm=0.05,
            root_span_mm=9.0,
        ),
        particles=(
            Particles(
                count=750.0,
                n_max=750,
                key=_preset_key(key, SEED_TAGS["particles"]),
                region="lens_nucleus",
                radius_mean_mm=0.01,
                radius_spread=0.3,
                region_radius_mm=2.5,
            ),
            Particles(
                count=250.0,
                n_max=250,
                key=_preset_key(key, SEED_TAGS["particles"] + 1),
                region="vitreous",
                radius_mean_mm=0.02,
                radius_spread=0.3,
                region_radius_mm=6.0,
            ),
        ),
        gratings=Gratings(
            count=200.0,
            n_max=200,
            key=_preset_key(key, SEED_TAGS["gratings"]),
            spacing_mm=0.04,
            line_thickness_mm=0.012,
            line_length_mm=0.3,
            inner_radius_mm=2.0,
            outer_radius_mm=3.5,
            lines_per_grating=5,
        ),
    )
