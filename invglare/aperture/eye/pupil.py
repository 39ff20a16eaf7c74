"""The pupil opening and the eyelids of the eye's aperture.

Lengths in mm in the pupil plane, angles in degrees counter-clockwise from +x towards
+y; the eye's axis is the grid's origin, and y points up (the upper lid is at y > 0).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from invglare._core.checks import as_float, check_range, choose, is_concrete
from invglare._core.grids import ApertureGrid
from invglare.aperture._checks import check_finite
from invglare.aperture.shapes.coverage import curved_edge_coverage
from invglare.aperture.shapes.primitives import Ellipse
from invglare.errors import PhysicsRangeError

#: Which lid a row of lashes hangs from.
LIDS = ("upper", "lower")


class Pupil(eqx.Module):
    """The pupil opening: an ellipse (a circle by default).

    **Arguments:**

    - `diameter_mm`: pupil diameter (major axis), > 0. About 2-3 mm in daylight and
      7-8 mm at night.
    - `ellipticity`: in ``[0, 1)``; the minor axis is ``diameter * (1 - ellipticity)``.
    - `rotation_deg`: direction of the major axis, from +x.
    - `decentration_mm`: (x, y) offset of the pupil centre from the eye's axis.
    """

    diameter_mm: Float[Array, ""] = eqx.field(converter=as_float)
    ellipticity: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)
    rotation_deg: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)
    decentration_mm: Float[Array, " 2"] = eqx.field(converter=as_float, default=(0.0, 0.0))

    def __check_init__(self):
        check_range("pupil diameter_mm", self.diameter_mm, 0.0, lo_open=True, unit="mm")
        check_range("pupil ellipticity", self.ellipticity, 0.0, 1.0)
        if is_concrete(self.ellipticity) and float(self.ellipticity) >= 1.0:
            raise PhysicsRangeError(f"pupil ellipticity must be < 1, got {float(self.ellipticity)}")
        check_finite("pupil rotation_deg", self.rotation_deg, ())
        check_finite("pupil decentration_mm", self.decentration_mm, (2,))

    def shape(self) -> Ellipse:
        """The pupil as an open :class:`~invglare.aperture.Ellipse`."""
        return Ellipse(self.diameter_mm, self.ellipticity, self.rotation_deg, self.decentration_mm)

    def coverage(self, grid: ApertureGrid) -> Float[Array, "n n"]:
        """Fraction of each pixel inside the pupil."""
        return self.shape().coverage(grid)

    def extent_radius_mm(self) -> float:
        """Distance (mm) from the axis to the farthest point of the pupil (concrete)."""
        return float(np.hypot(*np.asarray(self.decentration_mm))) + 0.5 * float(self.diameter_mm)


class Eyelids(eqx.Module):
    """Upper and lower eyelids: occluders beyond two gently curved margins.

    Each lid margin is the parabola ``y' = opening - curvature * x'**2 / 2`` in the
    lid's own frame (rotated by its tilt about the eye's axis; ``y'`` points away
    from the axis, up for the upper lid and down for the lower one), and the lid
    covers everything beyond it. A blink is both openings at 0 (with equal tilts, so
    that the margins meet; unequal tilts leave a wedge open on one side); squinting is
    any smaller opening: only parameter changes.

    **Arguments:**

    - `upper_opening_mm`, `lower_opening_mm`: distance (mm, >= 0) from the eye's axis
      to each lid margin (defaults 4.5 and 4.0: a relaxed, wide-open eye).
    - `upper_tilt_deg`, `lower_tilt_deg`: counter-clockwise rotation of each margin.
    - `curvature_per_mm`: curvature (1/mm, >= 0) of both margins at their apex; the
      default 0.04 closes a 4.5 mm opening over 15 mm, about a real palpebral fissure.

    The two lids' coverages are added (they do not overlap within a pixel while the
    eye is open) and clipped to 1, so two margins meeting at the axis close it
    completely.
    """

    upper_opening_mm: Float[Array, ""] = eqx.field(converter=as_float, default=4.5)
    lower_opening_mm: Float[Array, ""] = eqx.field(converter=as_float, default=4.0)
    upper_tilt_deg: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)
    lower_tilt_deg: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)
    curvature_per_mm: Float[Array, ""] = eqx.field(converter=as_float, default=0.04)

    def __check_init__(self):
        check_range("lids upper_opening_mm", self.upper_opening_mm, 0.0, unit="mm")
        check_range("lids lower_opening_mm", self.lower_opening_mm, 0.0, unit="mm")
        check_finite("lids upper_tilt_deg", self.upper_tilt_deg, ())
        check_finite("lids lower_tilt_deg", self.lower_tilt_deg, ())
        check_range("lids curvature_per_mm", self.curvature_per_mm, 0.0, unit="1/mm")

    def _lid(self, lid: str) -> tuple[Array, Array, float]:
        """(opening mm, tilt rad, sign of y' in the lid frame)."""
        choose("lid", lid, LIDS)
        if lid == "upper":
            return self.upper_opening_mm, jnp.deg2rad(self.upper_tilt_deg), 1.0
        return self.lower_opening_mm, jnp.deg2rad(self.lower_tilt_deg), -1.0

    def margin(
        self, lid: str, x_mm: Float[ArrayLike, " m"], shift_mm: ArrayLike = (0.0, 0.0)
    ) -> tuple[Float[Array, "m 2"], Float[Array, "m 2"]]:
        """Points on a lid margin and the unit normals there pointing into the opening.

        `x_mm` is the position along the margin in the lid's frame (0 at its apex);
        `shift_mm` translates the lids (the obstacle shift).
        """
        opening, tilt, sign = self._lid(lid)
        kappa = self.curvature_per_mm
        x = jnp.asarray(x_mm)
        y_lid = sign * (opening - 0.5 * kappa * x * x)
        g = jnp.sqrt(1.0 + (kappa * x) ** 2)
        nx_lid, ny_lid = -kappa * x / g, -sign / g
        c, s = jnp.cos(tilt), jnp.sin(tilt)
        shift = as_float(shift_mm)
        points = jnp.stack([c * x - s * y_lid + shift[0], s * x + c * y_lid + shift[1]], -1)
        normals = jnp.stack([c * nx_lid - s * ny_lid, s * nx_lid + c * ny_lid], -1)
        return points, normals

    def lid_coverage(
        self, grid: ApertureGrid, lid: str, shift_mm: ArrayLike = (0.0, 0.0)
    ) -> Float[Array, "n n"]:
        """Fraction of each pixel covered by one lid (``"upper"`` or ``"lower"``)."""
        opening, tilt, sign = self._lid(lid)
        kappa = self.curvature_per_mm
        shift = as_float(shift_mm)
        y, x = grid.mesh_mm()
        px, py = x - shift[0], y - shift[1]
        c, s = jnp.cos(tilt), jnp.sin(tilt)
        x_lid = c * px + s * py
        y_away = sign * (-s * px + c * py)  # distance from the axis towards the lid
        # f > 0 inside the lid; f / |grad f| is the signed distance to first order, exact
        # on the margin.
        f = y_away - opening + 0.5 * kappa * x_lid * x_lid
        g = jnp.sqrt(1.0 + (kappa * x_lid) ** 2)
        sd = -f / g
        # Outward normal of the lid region (towards the opening), back in grid axes.
        nx_lid, ny_lid = -kappa * x_lid / g, -sign / g
        nx = c * nx_lid - s * ny_lid
        ny = s * nx_lid + c * ny_lid
        # The lid region is concave along its margin: negative curvature.
        curvature = -kappa / g**3
        pitch = grid.pitch_mm
        return curved_edge_coverage(sd * (1.0 / pitch), nx, ny, curvature * pitch)

    def coverage(self, grid: ApertureGrid, shift_mm: ArrayLike = (0.0, 0.0)) -> Float[Array, "n n"]:
        """Fraction of each pixel covered by either lid, ``min(1, c_upper + c_lower)``."""
        both = self.lid_coverage(grid, "upper", shift_mm) + self.lid_coverage(
            grid, "lower", shift_mm
        )
        return jnp.clip(both, 0.0, 1.0)

    def transmission(
        self, grid: ApertureGrid, shift_mm: ArrayLike = (0.0, 0.0)
    ) -> Float[Array, "n n"]:
        """``1 - coverage``: what the lids let through."""
        return 1.0 - self.coverage(grid, shift_mm)
