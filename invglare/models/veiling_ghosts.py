"""Where the ghosts of a veiling-glare model come from: free parameters or a lens.

Two ghost *sources* feed :class:`invglare.models.veiling.VeilingGlare`; both answer
``at(light_angle_deg, profile)`` with the :class:`GhostSet` seen for a light in that
direction, and ``direct_fraction(light_angle_deg)`` with the fraction of the light
that forms the source's direct image.

- :class:`GhostSet`: ghosts given by their parameters (what a fit adjusts). Each
  ghost has a centre, a radius, a peak intensity and an edge softness, and moves
  with the light along the line through the screen centre: its centre is
  ``position_deg + ratio * screen_position_deg(light_angle_deg)``, the paraxial law (a
  ghost's image height is a fixed multiple of the source's, sec. 8) on the screen
  below; ``ratio = 0`` pins a ghost to the screen.
- :class:`LensGhosts`: ghosts computed from a lens prescription by paraxial matrix
  optics (:mod:`invglare.optics.paraxial`): for every path with 2, 4, ... reflections,
  the spot's centre, size and energy on the sensor, as functions of the light
  direction and of every lens parameter (curvatures, spacings, indices, coating
  reflectances, semi-apertures).

**Screen coordinates.** The screen is the sensor plane, measured in units of the
effective focal length and written in degrees: a sensor point at ``(x, y)`` mm is at
``deg(x / EFL), deg(y / EFL)`` (:func:`screen_position_deg` of its field angle is
``deg(tan(angle))``), with the optical axis at the centre. One linear mapping serves
ghost centres and radii alike, so a paraxial spot (a disk on the sensor) stays a disk
of the right size wherever it lands; it is a rectilinear camera's frame, uniform in
sensor millimetres. For small angles a screen degree is a degree of field angle (the
two differ by 1 % at 10 deg, 9 % at 30 deg); a light at direction ``a`` has its direct
image at ``screen_position_deg(a)``, and a screen point ``s`` is the image of the
direction :func:`direction_of_screen_deg` ``(s) = deg(atan(s))``. x grows with the
column, y with the row (row 0 first): in a frame shown with row 0 at the top, as image
files are, +y points *down* the picture. ``light_angle_deg`` uses the same axes, so a
light at ``(a_x, a_y)`` with ``a_y > 0`` images below the centre row of that display.

**Intensity.** A ghost's `intensity_per_sr` is the peak value of its glare spread
function, in sr⁻¹ (fraction of the source's flux per steradian of field), so a
ghost of profile ``p`` and radius ``R`` (rad) carries ``intensity x area(p) x R^2`` of
the flux (:func:`invglare.models.veiling_series.profile_area`).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from invglare._core.checks import as_float, is_concrete
from invglare.errors import ConfigError, PhysicsRangeError
from invglare.models.veiling_series import PROFILES, profile_area
from invglare.optics.paraxial import Lens, ghost_paths, ghost_spots

__all__ = ["GhostSet", "LensGhosts", "direction_of_screen_deg", "screen_position_deg"]


def screen_position_deg(light_angle_deg: Float[ArrayLike, "*shape"]) -> Float[Array, "*shape"]:
    """Where a light's direct image lands on the screen (deg), per axis: ``deg(tan(angle))``.

    The screen is the sensor in units of the EFL (see the module docstring); each axis's
    slope is ``tan`` of that axis's angle, as for the paraxial ghost trace.
    """
    return jnp.rad2deg(jnp.tan(jnp.deg2rad(as_float(light_angle_deg))))


def direction_of_screen_deg(screen_deg: Float[ArrayLike, "*shape"]) -> Float[Array, "*shape"]:
    """The light direction (deg) whose direct image lands at `screen_deg`: ``deg(atan(s))``.

    The inverse of :func:`screen_position_deg`, e.g. for the light of a frame's pixel.
    """
    return jnp.rad2deg(jnp.arctan(jnp.deg2rad(as_float(screen_deg))))



def _check_ghost_values(ghosts: GhostSet) -> None:
    k = ghosts.radius_deg.shape[0] if ghosts.radius_deg.ndim == 1 else None
    shapes = {
        "position_deg": (ghosts.position_deg, (k, 2)),
        "radius_deg": (ghosts.radius_deg, (k,)),
        "intensity_per_sr": (ghosts.intensity_per_sr, (k,)),
        "softness_deg": (ghosts.softness_deg, (k,)),
        "ratio": (ghosts.ratio, (k,)),
        "transmission": (ghosts.transmission, ()),
    }
    for name, (value, shape) in shapes.items():
        if k is None or value.shape != shape:
            raise PhysicsRangeError(
                f"ghost {name} must have shape {shape if k is not None else '(K,)'}, "
                f"got {value.shape}"
            )
    if not all(is_concrete(v) for v, _ in shapes.values()):
        return
    arrays = {name: np.asarray(v, dtype=float) for name, (v, _) in shapes.items()}
    for name, arr in arrays.items():
        if not np.all(np.isfinite(arr)):
            raise PhysicsRangeError(f"ghost {name} must be finite, got {arr.tolist()}")
    rules = [
        ("radius_deg", arrays["radius_deg"] <= 0, "> 0 deg"),
        ("intensity_per_sr", arrays["intensity_per_sr"] < 0, ">= 0 sr^-1"),
        ("softness_deg", arrays["softness_deg"] < 0, ">= 0 deg"),
    ]
    for name, bad, expected in rules:
        if np.any(bad):
            i = int(np.argmax(bad))
            raise PhysicsRangeError(f"ghost {i}: {name} = {arrays[name][i]:g}, expected {expected}")
    t = float(arrays["transmission"])
    if not 0.0 <= t <= 1.0:
        raise PhysicsRangeError(f"transmission = {t:g}, expected a fraction in [0, 1]")


class GhostSet(eqx.Module):
    """Ghosts given by their parameters, for a fit or a hand-made look.

    **Fields** (``K`` ghosts; all are parameters):

    - `position_deg`: ``(K, 2)`` centre (x, y) on the screen for a light on the axis (deg;
      the screen of the module docstring).
    - `radius_deg`: ``(K,)`` support radius (deg).
    - `intensity_per_sr`: ``(K,)`` peak of the ghost's glare spread function (sr⁻¹).
    - `softness_deg`: ``(K,)`` standard deviation of the Gaussian edge blur (deg).
    - `ratio`: ``(K,)`` how far the ghost moves per screen degree the light's direct image
      moves (0: fixed).
    - `transmission`: fraction of the light in the source's direct image (for the
      veiling glare index; 1 if unknown).

    Build one with :meth:`build`, which broadcasts scalars.
    """

    position_deg: Float[Array, "K 2"] = eqx.field(converter=as_float)
    radius_deg: Float[Array, " K"] = eqx.field(converter=as_float)
    intensity_per_sr: Float[Array, " K"] = eqx.field(converter=as_float)
    softness_deg: Float[Array, " K"] = eqx.field(converter=as_float)
    ratio: Float[Array, " K"] = eqx.field(converter=as_float)
    transmission: Float[Array, ""] = eqx.field(converter=as_float, default=1.0)

    def __check_init__(self):
        _check_ghost_values(self)

    @classmethod
    def build(
        cls,
        position_deg: Float[ArrayLike, "K 2"],
        radius_deg: Float[ArrayLike, "*K"],
        intensity_per_sr: Float[ArrayLike, "*K"],
        softness_deg: Float[ArrayLike, "*K"] = 0.0,
        ratio: Float[ArrayLike, "*K"] = 0.0,
        transmission: float = 1.0,
    ) -> GhostSet:
        """Ghosts from per-ghost values; scalars are shared by every ghost.

        **Arguments:**

        - `position_deg`: ``(K, 2)`` centres for a light on the axis (deg).
        - `radius_deg`: support radii (deg, > 0).
        - `intensity_per_sr`: peak glare spread (sr⁻¹, >= 0).
        - `softness_deg`: edge blur (deg, >= 0).
        - `ratio`: motion with the light (dimensionless).
        - `transmission`: the direct image's share of the light.

        **Example:**

        ```python
        ghosts = GhostSet.build([[0.0, 0.0], [1.5, -0.5]], [2.0, 3.5], [0.01, 0.004],
                                softness_deg=0.05, ratio=[0.3, -0.8])
        ```
        """
        position = as_float(position_deg)
        if position.ndim != 2 or position.shape[-1] != 2:
            raise PhysicsRangeError(
                f"position_deg must have shape (K, 2), got {tuple(position.shape)}"
            )
        k = position.shape[0]

        def per_ghost(name, value):
            arr = as_float(value)
            if arr.ndim == 0:
                return jnp.full((k,), arr)
            if arr.shape != (k,):
                raise PhysicsRangeError(
                    f"{name} must be a number or {k} values (one per ghost), got shape {arr.shape}"
                )
            return arr

        return cls(
            position_deg=position,
            radius_deg=per_ghost("radius_deg", radius_deg),
            intensity_per_sr=per_ghost("intensity_per_sr", intensity_per_sr),
            softness_deg=per_ghost("softness_deg", softness_deg),
            ratio=per_ghost("ratio", ratio),
            transmission=transmission,
        )

    @property
    def n_ghosts(self) -> int:
        return int(self.radius_deg.shape[0])

    def at(self, light_angle_deg: Float[ArrayLike, " 2"], profile: str = "disk") -> GhostSet:
        """The ghosts for a light at `light_angle_deg` (deg): moved, with ``ratio`` 0.

        A ghost moves by ``ratio`` times the light's direct image on the screen,
        :func:`screen_position_deg` of the angle (the paraxial law, exact for a lens's
        ghosts). `profile` is accepted for symmetry with :meth:`LensGhosts.at` and
        unused: the intensities are given directly.
        """
        image = screen_position_deg(light_angle_deg)
        moved = self.position_deg + self.ratio[:, None] * image[None, :]
        return eqx.tree_at(
            lambda g: (g.position_deg, g.ratio), self, (moved, jnp.zeros_like(self.ratio))
        )

    def direct_fraction(self, light_angle_deg: Float[ArrayLike, " 2"] = (0.0, 0.0)) -> Array:
        """Fraction of the light in the direct image (the `transmission` field)."""
        return self.transmission

    def energy(self, profile: str = "disk") -> Float[Array, " K"]:
        """Fraction of the source's flux carried by each ghost, ``I area(p) R^2``."""
        radius_rad = jnp.deg2rad(self.radius_deg)
        return self.intensity_per_sr * profile_area(profile) * radius_rad**2


def _check_scalar(name: str, value, lo: float, unit: str) -> None:
    if not is_concrete(value):
        return
    arr = np.asarray(value, dtype=float)
    if arr.shape != () or not np.isfinite(arr) or arr < lo:
        raise PhysicsRangeError(f"{name} must be one finite number >= {lo:g} {unit}, got {arr}")


class LensGhosts(eqx.Module):
    """Ghosts of a lens prescription, by paraxial matrix optics (sec. 8).

    **Fields:**

    - `lens`: the :class:`~invglare.optics.paraxial.Lens` (its arrays are parameters).
    - `softness_deg`: edge blur given to every ghost (deg): paraxial spots have hard
      edges, real ones are softened by aberrations and defocus.
    - `min_radius_deg`: floor on the ghost radius (deg), combined as
      ``sqrt(r^2 + r_min^2)``: a ghost focused near the sensor would otherwise shrink
      to a point of unbounded intensity (that is a flare spot, not veiling glare).
    - `paths`: the reflection sequences (static; from :meth:`build`).

    **Example:**

    ```python
    source = LensGhosts.build(load_lens("cooke_triplet"), max_reflections=2)
    ghosts = source.at(jnp.array([5.0, 0.0]))      # a GhostSet, 21 ghosts
    ```
    """

    lens: Lens
    softness_deg: Float[Array, ""] = eqx.field(converter=as_float)
    min_radius_deg: Float[Array, ""] = eqx.field(converter=as_float)
    paths: tuple[tuple[int, ...], ...] = eqx.field(static=True)

    def __check_init__(self):
        _check_scalar("softness_deg", self.softness_deg, 0.0, "deg")
        _check_scalar("min_radius_deg", self.min_radius_deg, 0.0, "deg")
        if not self.paths:
            raise ConfigError(
                "the lens has no ghost paths: it needs at least two reflecting surfaces "
                "(an index change or a reflective sensor)"
            )

    @classmethod
    def build(
        cls,
        lens: Lens,
        max_reflections: int = 2,
        softness_deg: float = 0.05,
        min_radius_deg: float = 0.05,
    ) -> LensGhosts:
        """Enumerate the ghost paths of `lens` up to `max_reflections` (2, 4, ...).

        **Arguments:**

        - `lens`: the prescription (sensor distance as given; see
          :meth:`~invglare.optics.paraxial.Lens.focused`).
        - `max_reflections`: even number; 2 gives ``n (n - 1) / 2`` ghosts for ``n``
          reflecting surfaces, 4 adds the four-bounce paths (sec. 8.1).
        - `softness_deg`, `min_radius_deg`: as for the fields.
        """
        paths = ghost_paths(lens.reflecting_surfaces(), max_reflections)
        return cls(
            lens=lens,
            softness_deg=softness_deg,
            min_radius_deg=min_radius_deg,
            paths=paths,
        )

    @property
    def n_ghosts(self) -> int:
        return len(self.paths)

    @property
    def max_reflections(self) -> int:
        return max(len(p) for p in self.paths)

    def _to_screen(self, centre_mm, radius_mm):
        # One linear map for centres and radii (the module's screen): h / EFL.
        efl = self.lens.effective_focal_length_mm()
        return jnp.rad2deg(centre_mm / efl), radius_mm / jnp.abs(efl)

    def spots(
        self, light_angle_deg: Float[ArrayLike, " 2"] = (0.0, 0.0)
    ) -> tuple[Float[Array, "P 2"], Float[Array, " P"], Float[Array, " P"]]:
        """Paraxial ghost spots on the screen: centre (deg), radius (deg, unfloored), energy.

        Energies are fractions of the flux an on-axis source sends into the lens.
        """
        angle = as_float(light_angle_deg)
        slope = jnp.tan(jnp.deg2rad(angle))
        centre_mm, radius_mm, energy = ghost_spots(self.lens, self.paths, slope)
        centre_deg, radius_rad = self._to_screen(centre_mm, radius_mm)
        return centre_deg, jnp.rad2deg(radius_rad), energy

    def at(self, light_angle_deg: Float[ArrayLike, " 2"], profile: str = "disk") -> GhostSet:
        """The ghosts for a light at `light_angle_deg` (deg), as a :class:`GhostSet`.

        The intensity spreads each ghost's energy over its (floored) radius with the
        model's `profile`, so the flux is right whatever the profile.
        """
        if profile not in PROFILES:
            raise ConfigError(f"profile = {profile!r} is not one of {', '.join(PROFILES)}")
        centre_deg, radius_deg, energy = self.spots(light_angle_deg)
        radius_deg = jnp.sqrt(radius_deg**2 + self.min_radius_deg**2)
        radius_rad = jnp.deg2rad(radius_deg)
        intensity = energy / (profile_area(profile) * radius_rad**2)
        k = len(self.paths)
        return GhostSet(
            position_deg=centre_deg,
            radius_deg=radius_deg,
            intensity_per_sr=intensity,
            softness_deg=jnp.broadcast_to(self.softness_deg, (k,)),
            ratio=jnp.zeros((k,), dtype=radius_deg.dtype),
            transmission=self.direct_fraction(light_angle_deg),
        )

    def direct_fraction(self, light_angle_deg: Float[ArrayLike, " 2"] = (0.0, 0.0)) -> Array:
        """Share of the light in the direct image: Fresnel losses times paraxial vignetting."""
        slope = jnp.tan(jnp.deg2rad(as_float(light_angle_deg)))
        return ghost_spots(self.lens, ((),), slope)[2][0]
