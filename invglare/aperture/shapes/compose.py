"""Combining soft shapes into one aperture transmission.

Coverages are treated as independent soft masks: the open part of an aperture
is the union of its ``"open"`` shapes, ``1 - prod(1 - c_i)``, and every
``"block"`` shape multiplies the transmission by ``1 - c_j``. For shapes that do
not overlap inside a pixel this is exact; where they overlap it is the usual
probabilistic-OR approximation, smooth in every coverage.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from invglare._core.grids import ApertureGrid
from invglare.aperture.shapes.primitives import AbstractShape
from invglare.errors import ConfigError


def union(*coverages: Float[ArrayLike, "*shape"]) -> Float[Array, "*shape"]:
    """Soft union of coverages in ``[0, 1]``: ``1 - prod(1 - c_i)``.

    With no arguments the union is empty (0).
    """
    if not coverages:
        return jnp.asarray(0.0)
    missed = 1.0 - jnp.asarray(coverages[0])
    for c in coverages[1:]:
        missed = missed * (1.0 - jnp.asarray(c))
    return 1.0 - missed


def occlude(
    transmission: Float[ArrayLike, "*shape"], *coverages: Float[ArrayLike, "*shape"]
) -> Float[Array, "*shape"]:
    """Transmission after occluders of the given coverages: ``t * prod(1 - c_j)``."""
    out = jnp.asarray(transmission)
    for c in coverages:
        out = out * (1.0 - jnp.asarray(c))
    return out


def _as_shape_tuple(shapes: Sequence[AbstractShape] | AbstractShape) -> tuple:
    if isinstance(shapes, AbstractShape):
        return (shapes,)
    return tuple(shapes)


class Aperture(eqx.Module):
    """An aperture made of soft shapes.

    **Arguments:**

    - `shapes`: the shapes (a sequence; stored as a tuple). ``"open"`` shapes are
      united; ``"block"`` shapes occlude. Without any open shape the whole window
      is open, so a lone grating of capsules is an occluder in a full window.

    Parameters are addressed by path for fitting, e.g.
    ``eqx.tree_at(lambda ap: ap.shapes[0].diameter_mm, ap, 3.0)``.
    """

    shapes: tuple = eqx.field(converter=_as_shape_tuple)

    def __check_init__(self):
        for i, shape in enumerate(self.shapes):
            if not isinstance(shape, AbstractShape):
                raise ConfigError(
                    f"aperture shapes[{i}] must be a shape (Disk, Ellipse, RegularPolygon, "
                    f"Capsule, ImageMask), got {type(shape).__name__}"
                )

    def transmission(self, grid: ApertureGrid) -> Float[Array, "n n"]:
        """Amplitude transmission in ``[0, 1]`` on `grid` (float dtype of the grid)."""
        opens = [s.coverage(grid) for s in self.shapes if s.role == "open"]
        blocks = [s.coverage(grid) for s in self.shapes if s.role == "block"]
        if opens:
            base = union(*opens)
        else:
            base = jnp.ones((grid.npix, grid.npix), dtype=jnp.asarray(grid.pitch_mm).dtype)
        return occlude(base, *blocks)

    def open_area_mm2(self) -> Float[Array, ""] | None:
        """The opening's area (mm²) in closed form: a lone open shape's; None otherwise.

        Unions, occluders and image masks have none; a PSF then measures the power
        through the aperture on its raster (see :mod:`invglare.optics.fraunhofer`).
        """
        if len(self.shapes) == 1 and self.shapes[0].role == "open":
            return self.shapes[0].area_mm2()
        return None

    def extent_mm(self) -> float:
        """Diameter (mm) of the smallest disk centred on the origin containing the open shapes.

        Meant for choosing a default window, so it needs concrete parameters (not
        inside `jit`). If there is no open shape (the window itself is the opening)
        it is the extent of all the shapes instead.
        """
        if not self.shapes:
            raise ConfigError("the aperture has no shapes, so it has no extent")
        opens = [s for s in self.shapes if s.role == "open"] or list(self.shapes)
        return 2.0 * max(s.extent_radius_mm() for s in opens)
