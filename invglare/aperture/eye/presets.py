"""Two ready-made eyes: :func:`lashed_daylight_eye` and :func:`night_eye`.

They are not the eyes of the bundled examples ``examples/eye_daylight.toml`` and
``examples/eye_night.toml`` (those are built, and fitted, through
:func:`invglare.config.eye.eye_from_config`); each docstring says how they differ. The
benchmarks time these two.
"""

from __future__ import annotations

import warnings

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


# The parameters a preset gives its lashes and particles, in the order the presets list them
# (the other parameters keep their defaults).
_LASH_FIELDS = (
    "count",
    "n_max",
    "angular_spread_deg",
    "thickness_mm",
    "length_mm",
    "curvature_per_mm",
    "root_span_mm",
)
_PARTICLE_FIELDS = (
    "region",
    "count",
    "n_max",
    "radius_mean_mm",
    "radius_spread",
    "region_radius_mm",
)


def _lashes(key, lid: str, *values) -> Eyelashes:
    """A preset's row of lashes on `lid`, `values` as in ``_LASH_FIELDS``."""
    tag = SEED_TAGS[f"lashes_{lid}"]
    return Eyelashes(
        key=_preset_key(key, tag), lid=lid, **dict(zip(_LASH_FIELDS, values, strict=True))
    )


def _particles(key, index: int, *values) -> Particles:
    """A preset's `index`-th particle population, `values` as in ``_PARTICLE_FIELDS``."""
    tag = SEED_TAGS["particles"] + index
    return Particles(key=_preset_key(key, tag), **dict(zip(_PARTICLE_FIELDS, values, strict=True)))


def lashed_daylight_eye(key: Key[Array, ""] | int = 0) -> EyeAperture:
    """A bright-light eye: small pupil, slightly narrowed lids, both rows of lashes, a few
    cornea cells.

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
    `key` seeds every component (``fold_in(key, tag)``, as
    :func:`invglare.config.eye.eye_from_config` does with its seed).

    The daylight eye of ``examples/eye_daylight.toml`` (the bundled fit's) has the same
    pupil, upper lashes and cornea cells, but lids that cut into the pupil (openings 1.2
    and 1.4 mm), no lower lashes and the seed 7; this one keeps the lids clear of the
    pupil and hangs lashes from both, for the benchmarks' position-dependent masking.
    """
    return EyeAperture(
        pupil=Pupil(3.0),
        lids=Eyelids(2.2, 3.0, 0.0, 0.0, 0.04),
        upper_lashes=_lashes(key, "upper", 40.0, 48, 12.0, 0.06, 2.5, 0.05, 8.0),
        lower_lashes=_lashes(key, "lower", 20.0, 24, 15.0, 0.05, 2.0, -0.05, 7.0),
        particles=(_particles(key, 0, "cornea", 60.0, 64, 0.0075, 0.2, 5.5),),
    )


def daylight_eye(key: Key[Array, ""] | int = 0) -> EyeAperture:
    """The old name of :func:`lashed_daylight_eye`, kept working with a `DeprecationWarning`.

    Renamed because it is not the eye of ``examples/eye_daylight.toml``.
    """
    warnings.warn(
        "daylight_eye() is now lashed_daylight_eye(): it is not the eye of "
        "examples/eye_daylight.toml (build that one with invglare.config.eye.eye_from_config)",
        DeprecationWarning,
        stacklevel=2,
    )
    return lashed_daylight_eye(key)


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

    `key` seeds every component (``fold_in(key, tag)``, as
    :func:`invglare.config.eye.eye_from_config` does with its seed).

    The night eye of ``examples/eye_night.toml`` (the bundled fit's) is smaller: a
    6.5 mm pupil, no lashes, 150 lens-nucleus and 60 vitreous particles of radius 30 and 50 um,
    40 gratings of 0.16 mm spacing, seed 11. This one has Ritschel et al.'s counts.
    """
    return EyeAperture(
        pupil=Pupil(7.0),
        lids=Eyelids(4.5, 4.0, 0.0, 0.0, 0.04),
        upper_lashes=_lashes(key, "upper", 80.0, 96, 10.0, 0.08, 3.0, 0.05, 9.0),
        particles=(
            _particles(key, 0, "lens_nucleus", 750.0, 750, 0.01, 0.3, 2.5),
            _particles(key, 1, "vitreous", 250.0, 250, 0.02, 0.3, 6.0),
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
