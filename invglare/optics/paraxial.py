"""Paraxial matrix optics of a rotationally symmetric lens, and its ghost reflections.

A lens is a sequence of spherical surfaces (:class:`Lens`). Rays are described by
their height ``y`` (mm) and slope ``u`` (rad) and travel through *ray-transfer
matrices* acting on ``(y, u)``:

- transfer over a distance ``d``: ``[[1, d], [0, 1]]``;
- refraction at a surface of curvature ``c = 1/R`` from index ``n1`` into ``n2``
  (paraxial Snell's law ``n2 u2 = n1 u1 - (n2 - n1) c y``):
  ``[[1, 0], [-c (n2 - n1) / n2, n1 / n2]]``;
- reflection, in the *unfolded* picture used throughout: after a reflection the
  ray travels towards -z, and its slope is measured along its own direction of
  travel (``u = dy/ds``), so a flat mirror leaves ``(y, u)`` unchanged. A ray
  travelling forwards (+z) that reflects off a surface gets ``[[1, 0], [2c, 1]]``; a
  ray travelling backwards that reflects off a surface from behind sees the
  curvature mirrored and gets ``[[1, 0], [-2c, 1]]``. A backward refraction from
  the medium after a surface into the one before it is likewise the forward
  formula with the curvature mirrored: ``[[1, 0], [c (n_b - n_a) / n_b, n_a / n_b]]``.

Heights stay physical heights in the unfolded picture, so after an even number of
reflections the ray reaches the sensor with its true height.

**Ghosts** (Lee, *Parametric Veiling-Glare Rendering*, sec. 8). A ghost is light
that reflects an even number of times between surfaces before it reaches the
sensor: with two reflections it goes forward to surface ``j``, back to surface
``i < j``, and forward again; with four it bounces once more (``j1 > i1 < j2 > i2``),
and so on (:func:`ghost_paths`). For ``n`` reflecting surfaces there are
``n (n - 1) / 2`` two-reflection ghosts.

For a source at infinity in the direction with slopes ``u0 = (tan a_x, tan a_y)``
every ray entering at height ``y0`` (2-vector, at the first surface's vertex
plane) lands on the sensor at ``M11 y0 + M12 u0``, with ``M`` the path's matrix
(rotational symmetry makes the two axes independent). The set of entrance heights
that pass every aperture of the path is the intersection of disks, one per surface
crossing: ``|P_e y0 + Q_e u0| <= a_e`` (``P_e, Q_e`` the first row of the matrix up
to that crossing, ``a_e`` the semi-aperture). Approximation used here (document
of record; see :func:`ghost_spots`):

- the ghost's pupil is the disk of its *limiting* crossing, the one with the
  smallest ``a_e / |P_e|`` (exact on axis, where all disks are concentric); when
  several crossings limit almost equally, the pupil's centre is their softly
  weighted mean, so that it moves continuously with the lens parameters;
- off axis the disks slide apart; the ghost keeps the size of its limiting disk's
  image and is dimmed by the *smallest* overlap of that disk with any other
  crossing's disk (exact circle–circle areas). The true transmitted area is the
  intersection of all disks, which this bounds from above; the two agree when one
  aperture does the vignetting, the usual case;
- the spot on the sensor is then a uniform disk (a linear map of a uniformly lit
  disk), of centre ``M11 c* + M12 u0`` and radius ``|M11| rho*``.

Energies are fractions of the flux an on-axis source sends through the lens's
entrance pupil (the limiting disk of the direct, image-forming path), times the
Fresnel factors: ``1 - R`` for every refraction at a surface with coating
reflectance ``R`` and ``R`` for every reflection. Absorption in the glass and
the angular dependence of the coating reflectance are neglected.

Everything is `jax.numpy` and differentiable in the lens parameters and the
light direction; the ghost paths are static (enumerated once from the lens
layout).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from invglare._core.checks import as_float, is_concrete
from invglare._core.maths import safe_sqrt
from invglare.errors import ConfigError, PhysicsRangeError

__all__ = [
    "Lens",
    "circle_overlap_area",
    "ghost_paths",
    "ghost_spots",
    "path_events",
    "reflection_matrix",
    "refraction_matrix",
    "system_matrix",
    "transfer_matrix",
]

# Event kinds along a path (static integer codes).
_PAD, _FWD, _BWD, _REFLECT_FWD, _REFLECT_BWD = 0, 1, 2, 3, 4
# Stand-in semi-aperture (mm) of the sensor plane, which clips nothing.
_NO_CLIP_MM = 1.0e6
# How sharply the limiting crossing is chosen: crossings whose ratio |P| / a is 1 %
# below the largest get weight exp(-1) relative to it.
_TIE_SHARPNESS = 100.0


# ------------------------------------------------------------------------------ matrices


def transfer_matrix(distance_mm: Float[ArrayLike, ""]) -> Float[Array, "2 2"]:
    """Ray-transfer matrix of a straight run of `distance_mm` (mm, along the ray).

    **Example:**

    ```python
    transfer_matrix(10.0) @ jnp.array([1.0, 0.1])   # height 1 mm -> 2 mm
    ```
    """
    d = as_float(distance_mm)
    one, zero = jnp.ones_like(d), jnp.zeros_like(d)
    return jnp.stack([jnp.stack([one, d]), jnp.stack([zero, one])])


def refraction_matrix(
    curvature_per_mm: Float[ArrayLike, ""],
    n_from: Float[ArrayLike, ""],
    n_to: Float[ArrayLike, ""],
    backward: bool = False,
) -> Float[Array, "2 2"]:
    """Paraxial refraction at a spherical surface.

    **Arguments:**

    - `curvature_per_mm`: ``1 / R`` (1/mm; positive when the centre of curvature
      lies after the surface, 0 for a flat).
    - `n_from`, `n_to`: refractive indices on the incoming and outgoing side.
    - `backward`: the ray travels towards -z (after a reflection); the surface is
      then seen mirrored (curvature ``-c``).

    **Example:**

    ```python
    # a 50 mm radius air-glass surface: power (1.5 - 1) / 50 per mm
    refraction_matrix(1 / 50.0, 1.0, 1.5)
    ```
    """
    c = as_float(curvature_per_mm)
    c = -c if backward else c
    n1, n2 = as_float(n_from), as_float(n_to)
    one, zero = jnp.ones_like(c * n1), jnp.zeros_like(c * n1)
    return jnp.stack([jnp.stack([one, zero]), jnp.stack([-c * (n2 - n1) / n2, n1 / n2])])


def reflection_matrix(
    curvature_per_mm: Float[ArrayLike, ""], backward: bool = False
) -> Float[Array, "2 2"]:
    """Paraxial reflection at a spherical surface, in the unfolded picture.

    A ray travelling forwards gets ``u -> u + 2 c y`` (a concave mirror, ``c < 0``
    as seen from the incoming side, focuses at ``|R| / 2``); one travelling backwards
    sees the surface mirrored, ``u -> u - 2 c y``.

    **Example:**

    ```python
    reflection_matrix(-1 / 100.0)   # concave mirror of focal length 50 mm
    ```
    """
    c = as_float(curvature_per_mm)
    c = -c if backward else c
    one, zero = jnp.ones_like(c), jnp.zeros_like(c)
    return jnp.stack([jnp.stack([one, zero]), jnp.stack([2.0 * c, one])])


# ------------------------------------------------------------------------------ lens


def _check_lens_values(lens: Lens) -> None:
    fields = {
        "curvature_per_mm": lens.curvature_per_mm,
        "thickness_mm": lens.thickness_mm,
        "index": lens.index,
        "semi_aperture_mm": lens.semi_aperture_mm,
        "reflectance": lens.reflectance,
    }
    n = None
    for name, value in fields.items():
        if value.ndim != 1:
            raise PhysicsRangeError(
                f"lens {name} must be one value per surface (1-D), got shape {value.shape}"
            )
        n = value.shape[0] if n is None else n
        if value.shape[0] != n:
            raise PhysicsRangeError(
                f"lens {name} has {value.shape[0]} entries but the lens has {n} surfaces"
            )
    if n == 0:
        raise PhysicsRangeError("a lens needs at least one surface, got none")
    if not 0 <= lens.stop_index < n:
        raise ConfigError(f"stop_index = {lens.stop_index} is not a surface (0..{n - 1})")
    if not all(is_concrete(v) for v in [*fields.values(), lens.sensor_reflectance]):
        return
    values = {k: np.asarray(v, dtype=float) for k, v in fields.items()}
    for name, arr in values.items():
        if not np.all(np.isfinite(arr)):
            raise PhysicsRangeError(f"lens {name} must be finite, got {arr.tolist()}")
    checks = [
        ("thickness_mm", values["thickness_mm"] < 0, ">= 0 mm"),
        ("index", values["index"] < 1.0, ">= 1 (a refractive index)"),
        ("semi_aperture_mm", values["semi_aperture_mm"] <= 0, "> 0 mm"),
        ("reflectance", (values["reflectance"] < 0) | (values["reflectance"] >= 1), "in [0, 1)"),
    ]
    for name, bad, expected in checks:
        if np.any(bad):
            i = int(np.argmax(bad))
            raise PhysicsRangeError(
                f"lens surface {i}: {name} = {values[name][i]:g}, expected {expected}"
            )
    r_sensor = float(np.asarray(lens.sensor_reflectance, dtype=float))
    if not 0.0 <= r_sensor < 1.0:
        raise PhysicsRangeError(f"sensor_reflectance = {r_sensor:g}, expected a value in [0, 1)")
    if not lens.object_index >= 1.0:
        raise PhysicsRangeError(f"object_index = {lens.object_index:g}, expected >= 1")


class Lens(eqx.Module):
    """A rotationally symmetric lens: spherical surfaces in order, then the sensor.

    **Fields** (one entry per surface; array fields are parameters):

    - `curvature_per_mm`: ``1 / R`` of each surface (1/mm, 0 for a flat; positive when
      the centre of curvature lies on the sensor side).
    - `thickness_mm`: distance from each surface's vertex to the next one; the last
      entry is the distance from the last surface to the sensor.
    - `index`: refractive index of the medium *after* each surface.
    - `semi_aperture_mm`: clear semi-aperture of each surface (for the stop: its radius).
    - `reflectance`: coating reflectance of each surface (0 for the stop and any
      surface without an index change).
    - `sensor_reflectance`: reflectance of the sensor (0: the sensor makes no ghosts).
    - `stop_index`: which surface is the aperture stop (static).
    - `object_index`: index of the medium in front of the lens (static, air = 1).
    - `name`: a label (static).

    Build one with :meth:`from_radii` when you have radii of curvature.
    """

    curvature_per_mm: Float[Array, " S"] = eqx.field(converter=as_float)
    thickness_mm: Float[Array, " S"] = eqx.field(converter=as_float)
    index: Float[Array, " S"] = eqx.field(converter=as_float)
    semi_aperture_mm: Float[Array, " S"] = eqx.field(converter=as_float)
    reflectance: Float[Array, " S"] = eqx.field(converter=as_float)
    sensor_reflectance: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)
    stop_index: int = eqx.field(static=True, default=0)
    object_index: float = eqx.field(static=True, default=1.0)
    name: str = eqx.field(static=True, default="")

    def __check_init__(self):
        _check_lens_values(self)

    @classmethod
    def from_radii(
        cls,
        radius_mm: Sequence[float],
        thickness_mm: Sequence[float],
        index: Sequence[float],
        semi_aperture_mm: Sequence[float],
        *,
        stop_index: int,
        reflectance: float | Sequence[float] = 0.0,
        sensor_reflectance: float = 0.0,
        object_index: float = 1.0,
        name: str = "",
    ) -> Lens:
        """A lens from radii of curvature (mm; 0 or ``inf`` for a flat surface).

        **Arguments:**

        - `radius_mm`, `thickness_mm`, `index`, `semi_aperture_mm`: per surface, as
          for the fields (`thickness_mm`'s last entry: last surface to sensor, mm).
        - `stop_index`: the aperture stop's surface.
        - `reflectance`: one value per surface, or one coating reflectance for every
          surface between glass and air (index 1 on one side); cemented glass-glass
          surfaces then get the uncoated normal-incidence Fresnel reflectance
          ``((n1 - n2) / (n1 + n2))^2``, which is tiny for similar glasses. Surfaces
          without an index change (the stop, dummy planes) always get 0: there is
          nothing to reflect there.
        - `sensor_reflectance`, `object_index`, `name`: as for the fields.

        **Example:**

        ```python
        singlet = Lens.from_radii([51.5, -51.5], [4.0, 48.0], [1.5168, 1.0],
                                  [10.0, 10.0], stop_index=0, reflectance=0.04)
        singlet.effective_focal_length_mm()   # ~50.5 mm
        ```
        """
        radii = np.asarray(radius_mm, dtype=float)
        flat = (radii == 0) | ~np.isfinite(radii)
        curvature = np.where(flat, 0.0, 1.0 / np.where(flat, 1.0, radii))
        n_after = np.asarray(index, dtype=float)
        n_before = np.concatenate([[object_index], n_after[:-1]])
        if np.ndim(reflectance) == 0:
            facing_air = np.isclose(n_before, 1.0) | np.isclose(n_after, 1.0)
            fresnel = ((n_before - n_after) / (n_before + n_after)) ** 2
            refl = np.where(facing_air, float(reflectance), fresnel)
        else:
            refl = np.asarray(reflectance, dtype=float)
            if refl.shape != n_after.shape:
                raise ConfigError(
                    f"reflectance has {refl.size} values but the lens has {n_after.size} surfaces"
                )
        refl = np.where(np.isclose(n_before, n_after), 0.0, refl)
        return cls(
            curvature_per_mm=curvature,
            thickness_mm=np.asarray(thickness_mm, dtype=float),
            index=n_after,
            semi_aperture_mm=np.asarray(semi_aperture_mm, dtype=float),
            reflectance=refl,
            sensor_reflectance=float(sensor_reflectance),
            stop_index=int(stop_index),
            object_index=float(object_index),
            name=name,
        )

    @property
    def n_surfaces(self) -> int:
        return int(self.curvature_per_mm.shape[0])

    def radius_mm(self) -> Float[Array, " S"]:
        """Radii of curvature (mm; ``inf`` for flat surfaces)."""
        c = self.curvature_per_mm
        return jnp.where(c == 0, jnp.inf, 1.0 / jnp.where(c == 0, 1.0, c))

    def index_before(self) -> Float[Array, " S"]:
        """Refractive index of the medium in front of each surface."""
        first = jnp.full((1,), self.object_index, dtype=self.index.dtype)
        return jnp.concatenate([first, self.index[:-1]])

    def reflecting_surfaces(self) -> tuple[int, ...]:
        """Surfaces that can reflect (index change), plus the sensor (index ``S``) if reflective.

        Decided from concrete values, so call it outside `jit` (it fixes the ghost paths).
        """
        n_b = np.asarray(self.index_before(), dtype=float)
        n_a = np.asarray(self.index, dtype=float)
        surfaces = [int(i) for i in np.nonzero(~np.isclose(n_b, n_a))[0]]
        if float(np.asarray(self.sensor_reflectance)) > 0.0:
            surfaces.append(self.n_surfaces)
        return tuple(surfaces)

    def matrix(self, last: int | None = None) -> Float[Array, "2 2"]:
        """Ray-transfer matrix from the first vertex to just after surface `last` (default: all).

        Transfers between surfaces are included; the final run to the sensor is not.
        """
        return system_matrix(self, last)

    def effective_focal_length_mm(self) -> Float[Array, ""]:
        """Paraxial effective focal length ``-1 / C`` of the whole lens (mm), object in air.

        **Example:**

        ```python
        cooke.effective_focal_length_mm()   # 101.18 for Smith's triplet
        ```
        """
        return -1.0 / self.matrix()[1, 0]

    def back_focal_distance_mm(self) -> Float[Array, ""]:
        """Distance from the last vertex to the rear focal point, ``-A / C`` (mm)."""
        m = self.matrix()
        return -m[0, 0] / m[1, 0]

    def axial_heights(self) -> Float[Array, " S"]:
        """Height at each surface of the axial ray entering parallel at height 1 mm.

        The marginal ray of a distant source on the axis, scaled: a beam entering with
        radius ``rho`` meets surface ``s`` with radius ``rho * |axial_heights()[s]|``.
        """
        n_b = self.index_before()
        y, u = jnp.ones((), self.curvature_per_mm.dtype), jnp.zeros((), self.index.dtype)
        heights = []
        for s in range(self.n_surfaces):
            heights.append(y)
            m = refraction_matrix(self.curvature_per_mm[s], n_b[s], self.index[s])
            y, u = m[0, 0] * y + m[0, 1] * u, m[1, 0] * y + m[1, 1] * u
            y = y + self.thickness_mm[s] * u
        return jnp.stack(heights)

    def entrance_pupil_radius_mm(self) -> Float[Array, ""]:
        """Radius (mm) of the widest axial beam from a distant source that every surface passes.

        ``min_s semi_aperture[s] / |axial_heights()[s]|``: the stop sets it when the lens
        is designed so, a smaller clear aperture before or after it otherwise (the
        axial beam is then vignetted, and the f-number slower than the stop's).
        """
        return jnp.min(self.semi_aperture_mm / jnp.abs(self.axial_heights()))

    def f_number(self) -> Float[Array, ""]:
        """Paraxial f-number of a distant source on the axis: ``EFL / (2 entrance radius)``."""
        return self.effective_focal_length_mm() / (2.0 * self.entrance_pupil_radius_mm())

    def focused(self) -> Lens:
        """A copy with the sensor at the rear focal plane (sharp image of a distant source)."""
        t = self.thickness_mm.at[-1].set(self.back_focal_distance_mm())
        return eqx.tree_at(lambda lens: lens.thickness_mm, self, t)

    def transmission(self) -> Float[Array, ""]:
        """Fraction of the entering flux left after every refraction's reflection loss."""
        return jnp.prod(1.0 - self.reflectance)


@eqx.filter_jit
def system_matrix(lens: Lens, last: int | None = None) -> Float[Array, "2 2"]:
    """Matrix of the image-forming (direct) path from the first vertex to after `last`.

    **Example:**

    ```python
    m = system_matrix(lens)        # [[A, B], [C, D]]; EFL = -1 / C
    ```
    """
    last = lens.n_surfaces - 1 if last is None else int(last)
    n_b = lens.index_before()
    m = jnp.eye(2, dtype=lens.curvature_per_mm.dtype)
    for s in range(last + 1):
        m = refraction_matrix(lens.curvature_per_mm[s], n_b[s], lens.index[s]) @ m
        if s < last:
            m = transfer_matrix(lens.thickness_mm[s]) @ m
    return m


# ------------------------------------------------------------------------------ ghost paths


def ghost_paths(reflecting: Sequence[int], max_reflections: int = 2) -> tuple[tuple[int, ...], ...]:
    """Every ghost path with 2, 4, ..., `max_reflections` reflections (sec. 8.1).

    A path is the tuple of surfaces where the light reflects, in order: the first
    is hit travelling forwards, the second (an earlier surface) travelling backwards,
    the third (a later surface than the second) forwards again, and so on; after the
    last reflection the light goes forward to the sensor.

    **Arguments:**

    - `reflecting`: indices of the surfaces that reflect (:meth:`Lens.reflecting_surfaces`).
    - `max_reflections`: an even number >= 2.

    **Returns:** the paths, shortest first; ``n (n - 1) / 2`` of length 2 for ``n``
    reflecting surfaces.

    **Example:**

    ```python
    ghost_paths([0, 1, 2])          # ((1, 0), (2, 0), (2, 1))
    ```
    """
    if isinstance(max_reflections, bool) or not isinstance(max_reflections, int | np.integer):
        raise ConfigError(f"max_reflections must be an even integer >= 2, got {max_reflections!r}")
    if max_reflections < 2 or max_reflections % 2:
        raise ConfigError(f"max_reflections must be an even integer >= 2, got {max_reflections}")
    surfaces = sorted({int(s) for s in reflecting})
    paths: list[tuple[int, ...]] = []

    def extend(prefix: tuple[int, ...], remaining: int) -> None:
        if remaining == 0:
            paths.append(prefix)
            return
        forward = len(prefix) % 2 == 0
        last = prefix[-1] if prefix else -1
        for s in surfaces:
            if (forward and s > last) or (not forward and s < last):
                extend((*prefix, s), remaining - 1)

    for k in range(2, max_reflections + 1, 2):
        start = len(paths)
        extend((), k)
        # Order each length group by its reflection sequence, for reproducible layouts.
        paths[start:] = sorted(paths[start:])
    return tuple(paths)


@functools.lru_cache(maxsize=64)
def path_events(
    paths: tuple[tuple[int, ...], ...], n_surfaces: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The surface crossings of each path, padded to a common length.

    **Returns:** ``(kind, surface, next_surface)``, int arrays of shape ``(P, L)``.
    `kind` is 1 forward refraction, 2 backward refraction, 3 reflection travelling
    forwards, 4 reflection travelling backwards, 0 padding (at the sensor, index
    ``n_surfaces``). The empty path ``()`` is the direct image.
    """
    rows = []
    for path in paths:
        events: list[tuple[int, int]] = []
        current, forward = -1, True
        for r in path:
            if forward:
                events += [(_FWD, s) for s in range(current + 1, r)] + [(_REFLECT_FWD, r)]
            else:
                events += [(_BWD, s) for s in range(current - 1, r, -1)] + [(_REFLECT_BWD, r)]
            current, forward = r, not forward
        if not forward:
            raise ConfigError(f"ghost path {path} has an odd number of reflections")
        events += [(_FWD, s) for s in range(current + 1, n_surfaces)]
        if any(s > n_surfaces or (s == n_surfaces and k != _REFLECT_FWD) for k, s in events):
            raise ConfigError(f"ghost path {path} uses a surface beyond the sensor")
        rows.append(events)
    length = max(1, *(len(e) for e in rows)) if rows else 1
    kind = np.full((len(rows), length), _PAD, dtype=np.int32)
    surface = np.full((len(rows), length), n_surfaces, dtype=np.int32)
    for p, events in enumerate(rows):
        for e, (k, s) in enumerate(events):
            kind[p, e], surface[p, e] = k, s
    next_surface = np.concatenate(
        [surface[:, 1:], np.full((len(rows), 1), n_surfaces, dtype=np.int32)], axis=1
    )
    return kind, surface, next_surface


# ------------------------------------------------------------------------------ geometry


def circle_overlap_area(
    r1: Float[ArrayLike, "*s"], r2: Float[ArrayLike, "*s"], d: Float[ArrayLike, "*s"]
) -> Float[Array, "*s"]:
    """Area of the intersection of two disks of radii `r1`, `r2` whose centres are `d` apart.

    Differentiable everywhere except at tangency; the unused branches are fed safe
    arguments so no NaN reaches a gradient.

    **Example:**

    ```python
    circle_overlap_area(1.0, 1.0, 0.0)   # pi
    ```
    """
    r1, r2, d = as_float(r1), as_float(r2), as_float(d)
    small, big = jnp.minimum(r1, r2), jnp.maximum(r1, r2)
    inside = d <= big - small
    apart = d >= r1 + r2
    partial = ~(inside | apart)
    tiny = 1e-30 + 1e-12 * big
    d_s = jnp.where(partial, d, 0.5 * (big - small + r1 + r2))
    d_s = jnp.maximum(d_s, tiny)
    # arccos and sqrt have infinite slopes at +-1 and 0 (tangency, and the far-apart
    # radii of the branches not taken): keep their arguments a hair inside.
    edge = 1.0 - 8.0 * jnp.finfo(d_s.dtype).eps
    a1 = (d_s**2 + r1**2 - r2**2) / (2 * d_s * jnp.maximum(r1, tiny))
    a2 = (d_s**2 + r2**2 - r1**2) / (2 * d_s * jnp.maximum(r2, tiny))
    a1 = jnp.clip(jnp.where(partial, a1, 0.0), -edge, edge)
    a2 = jnp.clip(jnp.where(partial, a2, 0.0), -edge, edge)
    k = (-d_s + r1 + r2) * (d_s + r1 - r2) * (d_s - r1 + r2) * (d_s + r1 + r2)
    k = jnp.where(partial & (k > 0), k, 1.0)
    root = jnp.where(partial & (k > 0), jnp.sqrt(k), 0.0)
    lens_area = r1**2 * jnp.arccos(a1) + r2**2 * jnp.arccos(a2) - 0.5 * root
    return jnp.where(inside, math.pi * small**2, jnp.where(apart, 0.0, lens_area))


def _event_matrices(kind, c, n_b, n_a):
    """Matrices of a batch of events (all kinds evaluated, the right one picked)."""
    eye = jnp.broadcast_to(jnp.eye(2, dtype=c.dtype), (*c.shape, 2, 2))
    fwd = jax.vmap(refraction_matrix)(c.ravel(), n_b.ravel(), n_a.ravel()).reshape(eye.shape)
    bwd = jax.vmap(lambda c_, a, b: refraction_matrix(c_, a, b, backward=True))(
        c.ravel(), n_a.ravel(), n_b.ravel()
    ).reshape(eye.shape)
    rf = jax.vmap(reflection_matrix)(c.ravel()).reshape(eye.shape)
    rb = jax.vmap(lambda c_: reflection_matrix(c_, backward=True))(c.ravel()).reshape(eye.shape)
    k = kind[..., None, None]
    out = jnp.where(k == _FWD, fwd, eye)
    out = jnp.where(k == _BWD, bwd, out)
    out = jnp.where(k == _REFLECT_FWD, rf, out)
    return jnp.where(k == _REFLECT_BWD, rb, out)


def _extended(lens: Lens):
    """Per-surface arrays with the sensor appended as surface ``S`` (flat, clips nothing)."""
    dtype = lens.curvature_per_mm.dtype
    zero = jnp.zeros((1,), dtype)
    n_b = lens.index_before()
    curvature = jnp.concatenate([lens.curvature_per_mm, zero])
    n_before = jnp.concatenate([n_b, lens.index[-1:]])
    n_after = jnp.concatenate([lens.index, lens.index[-1:]])
    semi = jnp.concatenate([lens.semi_aperture_mm, jnp.full((1,), _NO_CLIP_MM, dtype)])
    refl = jnp.concatenate([lens.reflectance, jnp.reshape(lens.sensor_reflectance, (1,))])
    z = jnp.concatenate([zero, jnp.cumsum(lens.thickness_mm)])
    return curvature, n_before, n_after, semi, refl, z


def _trace_paths(lens: Lens, paths: tuple[tuple[int, ...], ...]):
    """First-row matrix entries at every crossing, the full matrices and Fresnel factors."""
    kind_np, surf_np, next_np = path_events(paths, lens.n_surfaces)
    curvature, n_before, n_after, semi, refl, z = _extended(lens)
    kind, surf = jnp.asarray(kind_np), jnp.asarray(surf_np)
    events = _event_matrices(kind, curvature[surf], n_before[surf], n_after[surf])
    distance = jnp.abs(z[jnp.asarray(next_np)] - z[surf])
    factor = jnp.where(
        (kind == _FWD) | (kind == _BWD),
        1.0 - refl[surf],
        jnp.where(kind == _PAD, 1.0, refl[surf]),
    )
    clips = (kind != _PAD) & (surf < lens.n_surfaces)

    def step(m, xs):
        event, d = xs
        row = m[..., 0, :]  # (P, Q) of y = P y0 + Q u0 at this crossing
        m = jnp.einsum("pij,pjk->pik", event, m)
        t = jnp.stack(
            [
                jnp.stack([jnp.ones_like(d), d], -1),
                jnp.stack([jnp.zeros_like(d), jnp.ones_like(d)], -1),
            ],
            -2,
        )
        return jnp.einsum("pij,pjk->pik", t, m), row

    n_paths = kind.shape[0]
    m0 = jnp.broadcast_to(jnp.eye(2, dtype=curvature.dtype), (n_paths, 2, 2))
    m_final, rows = jax.lax.scan(
        step, m0, (jnp.moveaxis(events, 1, 0), jnp.moveaxis(distance, 1, 0))
    )
    rows = jnp.moveaxis(rows, 0, 1)  # (P, L, 2)
    return m_final, rows, semi[surf], clips, jnp.prod(factor, axis=1)


@eqx.filter_jit
def ghost_spots(
    lens: Lens,
    paths: tuple[tuple[int, ...], ...],
    slope: Float[ArrayLike, " 2"],
) -> tuple[Float[Array, "P 2"], Float[Array, " P"], Float[Array, " P"]]:
    """Centre, radius and energy of each path's spot on the sensor, for a distant source.

    **Arguments:**

    - `lens`: the :class:`Lens`.
    - `paths`: reflection sequences from :func:`ghost_paths`; ``((),)`` gives the direct
      image (its energy is the lens's transmission times its vignetting).
    - `slope`: ``(tan a_x, tan a_y)`` of the light's direction.

    **Returns:** ``(centre_mm, radius_mm, energy)``: the spot centres ``(P, 2)`` and
    radii ``(P,)`` on the sensor (mm), and the energies as fractions of the flux an
    on-axis source sends into the entrance pupil, including Fresnel factors and
    the vignetting approximation of the module docstring.

    **Example:**

    ```python
    paths = ghost_paths(lens.reflecting_surfaces(), 2)
    centre, radius, energy = ghost_spots(lens, paths, jnp.tan(jnp.deg2rad(jnp.array([5.0, 0.0]))))
    ```
    """
    slope = as_float(slope)
    all_paths = ((), *paths)
    m, rows, semi, clips, factor = _trace_paths(lens, all_paths)
    p_e, q_e = rows[..., 0], rows[..., 1]  # (P, L)
    # Limiting crossing: the one whose aperture, mapped back to the entrance plane, is
    # smallest (largest |P| / a). Non-clipping events get ratio 0.
    ratio = jnp.where(clips, jnp.abs(p_e) / semi, 0.0)
    top = jnp.max(ratio, axis=1)
    rho = 1.0 / top  # entrance-plane pupil radius of each path
    # Its centre, -Q/P u0. Crossings that limit almost equally (a sensor ghost's way to
    # the sensor and back mirror each other exactly when the sensor is at the focus)
    # share the role with soft weights, so the centre does not jump between them: two
    # equal disks intersect in a lens centred between them.
    weight = jnp.where(clips, jnp.exp(_TIE_SHARPNESS * (ratio / top[:, None] - 1.0)), 0.0)
    weight = weight / jnp.sum(weight, axis=1, keepdims=True)
    usable = clips & (jnp.abs(p_e) > 1e-12 * semi)
    offset = jnp.sum(jnp.where(usable, weight * q_e / jnp.where(usable, p_e, 1.0), 0.0), axis=1)
    centre0 = -offset[:, None] * slope[None, :]  # (P, 2)
    # Footprint of that pupil on every crossing vs. the crossing's aperture.
    foot_c = p_e[..., None] * centre0[:, None, :] + q_e[..., None] * slope
    foot_r = jnp.abs(p_e) * rho[:, None]
    # Norm with a zero gradient at 0 (every footprint is centred on the axis when u0 = 0).
    foot_d2 = jnp.sum(foot_c**2, axis=-1)
    foot_d = safe_sqrt(foot_d2)
    safe_r = jnp.maximum(foot_r, 1e-9 * semi)
    frac = circle_overlap_area(safe_r, semi, foot_d) / (math.pi * safe_r**2)
    frac = jnp.where(clips, jnp.clip(frac, 0.0, 1.0), 1.0)
    vignetting = jnp.min(frac, axis=1)
    m11, m12 = m[:, 0, 0], m[:, 0, 1]
    centre = m11[:, None] * centre0 + m12[:, None] * slope[None, :]
    radius = jnp.abs(m11) * rho
    # Areas relative to the direct path's entrance pupil (on axis, where it is exact).
    energy = factor * vignetting * (rho / rho[0]) ** 2
    return centre[1:], radius[1:], energy[1:]

def lens_to_table(lens: Lens) -> dict[str, Any]:
    """A lens as an inline table (every surface's reflectance explicit).

    ``lens_from_table(lens_to_table(lens)).lens`` rebuilds the same lens.
    """
    # Radii from the curvatures in float64, so that they convert back to the same values.
    curvature = np.asarray(lens.curvature_per_mm, dtype=float)
    flat = curvature == 0
    radius = np.where(flat, np.inf, 1.0 / np.where(flat, 1.0, curvature))
    surfaces = []
    for i in range(lens.n_surfaces):
        surface: dict[str, Any] = {
            "radius_mm": float(radius[i]) if np.isfinite(radius[i]) else 0.0,
            "thickness_mm": float(lens.thickness_mm[i]),
            "index": float(lens.index[i]),
            "semi_aperture_mm": float(lens.semi_aperture_mm[i]),
            "reflectance": float(lens.reflectance[i]),
        }
        if i == lens.stop_index:
            surface["stop"] = True
        surfaces.append(surface)
    table: dict[str, Any] = {
        "sensor_reflectance": float(lens.sensor_reflectance),
        "object_index": float(lens.object_index),
        "surfaces": surfaces,
    }
    if lens.name:
        table = {"name": lens.name, **table}
    return table
