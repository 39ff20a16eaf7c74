"""The one glare-model interface every model implements.

A glare model is a final subclass of :class:`AbstractGlareModel` (an equinox Module: its
array fields are the parameters a fit can free, its static fields configuration). Render,
psf, fit, sample, regress, bench, the torch layer and the batch fits reach a model
through this interface alone:

- ``model(light_angle_deg=None, *, state=None)`` → the image of one light, ``(ny, nx)``
  (one wavelength) or ``(ny, nx, 3)`` (linear RGB), in the documented normalisation;
- ``model.batch(light_angles_deg)`` → ``(K, ny, nx[, 3])`` for many lights;
- ``model.pixel_scale_deg``, ``model.wavelengths_nm``: the image's sampling and the
  wavelengths it is made at (None for a model drawn without a wavelength);
- ``model.shift_invariant``: whether one convolution renders a scene (the image does not
  depend on the light's direction), or each light needs its own image;
- ``model.centre`` (a class variable): ``"light"`` when an image is centred on the
  light's own image point (a PSF), ``"axis"`` when it covers the screen with the optical
  axis at its centre pixel (lens ghosts);
- ``model.animated`` (a class variable): whether the model has a state that evolves
  frame to frame (``init_state`` / ``advance``), so that ``invglare render --frames``
  can animate it;
- ``model.core_radius_px()``: the radius of the central diffraction spot (pixels), or
  None when the model has none; the Kakimoto tone map keeps that spot apart;
- ``model.header()``: plain values describing the image (normalisation, method) for file
  headers;
- ``model.sized_for(others)``: a copy whose static raster structure (the eye's stamp
  windows) holds every element of this model and of `others` (the same model at other
  parameter values, e.g. the corners of a fit's box); models without such structure
  return themselves;
- ``model.to_config()``: the config table that rebuilds it (``build_model``).

A model that renders a whole scene itself, from every pixel rather than light by light
(the holographic eye's point sources), sets the class variable ``renders_scenes`` and
implements ``render_scene(frame, depth, key, *, iterations=None, progress=False)``;
``invglare render`` then hands it the frame (and its depth buffer) as a whole.

**Light directions** are ``(x, y)`` in degrees: x to the right, as seen looking out
through the aperture, and y along the rows: every image a model returns has its y growing
with the row index (the grids' convention, :mod:`invglare._core.grids`), so +y is up
with row 0 at the bottom and *down* a frame shown with row 0 at the top, as image files
are (and as :func:`invglare.render.light_angles_deg` reads a frame's lights); ``None``
means the model's own default direction (on axis, or the direction leaf a fit adjusts).
**State**: animated models take the frame's state as the keyword `state` (``None``: at
rest); static models accept only ``state=None``.

Adding a model is its file here plus one registration in :mod:`invglare.config.kinds`
(see ``CONTRIBUTING.md``).
"""

# No `from __future__ import annotations` here: equinox reads the AbstractVar and
# AbstractClassVar annotations as objects when the class is created.
import abc
from collections.abc import Sequence
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from invglare._core.checks import as_float, is_concrete
from invglare.errors import ConfigError, PhysicsRangeError

#: The values of :attr:`AbstractGlareModel.centre`.
CENTRES = ("light", "axis")

Image = Float[Array, "ny nx"] | Float[Array, "ny nx 3"]
Images = Float[Array, "K ny nx"] | Float[Array, "K ny nx 3"]


class AbstractGlareModel(eqx.Module):
    """The interface of every glare model (see the module docstring)."""

    #: Degrees of field per image pixel (a field or a property; an array leaf where a fit
    #: may free it, so ``float()`` it outside `jit`).
    pixel_scale_deg: eqx.AbstractVar[float | Float[Array, ""]]
    centre: eqx.AbstractClassVar[str]
    animated: eqx.AbstractClassVar[bool]
    #: True for a model that renders a whole scene itself (see the module docstring).
    renders_scenes: ClassVar[bool] = False

    @abc.abstractmethod
    def __call__(
        self, light_angle_deg: Float[ArrayLike, " 2"] | None = None, *, state: Any = None
    ) -> Image:
        """The image of a light at `light_angle_deg` (deg, ``(x, y)``; None: the default)."""

    @abc.abstractmethod
    def batch(
        self, light_angles_deg: Float[ArrayLike, "K 2"], batch_size: int | None = None
    ) -> Images:
        """Images of many lights, ``(K, ...)``; `batch_size` at a time when given."""

    @property
    @abc.abstractmethod
    def wavelengths_nm(self) -> tuple[float, ...] | None:
        """The wavelengths (nm) the image is made at; None for a model without any."""

    @property
    @abc.abstractmethod
    def shift_invariant(self) -> bool:
        """True when the image does not depend on the light's direction."""

    @abc.abstractmethod
    def core_radius_px(self) -> float | None:
        """Radius (image pixels) of the central diffraction spot, or None."""

    @abc.abstractmethod
    def header(self) -> dict[str, Any]:
        """Plain values describing the image for a file header (normalisation, method)."""

    @abc.abstractmethod
    def sized_for(self, others: Sequence["AbstractGlareModel"]) -> "AbstractGlareModel":
        """A copy whose static raster structure also holds every element of `others`."""

    @abc.abstractmethod
    def to_config(self) -> dict[str, Any]:
        """The config (``{"model": ..., ...}``) that rebuilds this model."""


class AbstractShiftInvariantModel(AbstractGlareModel):
    """A model whose image is the same for every light direction: its :meth:`psf`, made
    once for a whole batch."""

    @abc.abstractmethod
    def psf(self) -> Image:
        """The image of every light (an animated model's at rest)."""

    def batch(
        self, light_angles_deg: Float[ArrayLike, "K 2"], batch_size: int | None = None
    ) -> Images:
        """The image once per light, ``(K, ...)`` (computed once)."""
        return broadcast_image(self.psf(), light_angles(light_angles_deg).shape[0])

    @property
    def shift_invariant(self) -> bool:
        return True


def check_light_angle(light_angle_deg: Array, batched: bool = False) -> None:
    """Shape ``(2,)`` (or ``(K, 2)``); concrete values finite and within ±90 deg."""
    expected = "(K, 2)" if batched else "(2,)"
    if light_angle_deg.ndim != (2 if batched else 1) or light_angle_deg.shape[-1] != 2:
        raise PhysicsRangeError(
            f"light_angle_deg must have shape {expected} (x, y angles in deg), "
            f"got shape {light_angle_deg.shape}"
        )
    if not is_concrete(light_angle_deg):
        return
    arr = np.asarray(light_angle_deg, dtype=float)
    if not np.all(np.isfinite(arr)) or np.any(np.abs(arr) >= 90.0):
        raise PhysicsRangeError(
            f"light_angle_deg must be finite and within (-90, 90) deg, got {arr.tolist()}"
        )


def light_angle(
    light_angle_deg: Float[ArrayLike, " 2"] | None, default: Float[ArrayLike, " 2"] = (0.0, 0.0)
) -> Float[Array, " 2"]:
    """A light direction as a checked float array; None is `default`."""
    angle = as_float(default if light_angle_deg is None else light_angle_deg)
    check_light_angle(angle)
    return angle


def light_angles(light_angles_deg: Float[ArrayLike, "K 2"]) -> Float[Array, "K 2"]:
    """Many light directions ``(K, 2)`` as a checked float array."""
    angles = as_float(light_angles_deg)
    check_light_angle(angles, batched=True)
    return angles


def check_no_state(model: AbstractGlareModel, state: Any) -> None:
    """Static models take no state: refuse one, naming the model."""
    if state is not None:
        raise ConfigError(
            f"{type(model).__name__} is a static model and takes no state; "
            "only animated models (e.g. kind = 'temporal') do"
        )


def map_lights(fn, angles: Array, batch_size: int | None) -> Array:
    """``fn`` over the lights ``(K, 2)``: one ``vmap``, or `batch_size` at a time."""
    if batch_size is None:
        return jax.vmap(fn)(angles)
    return jax.lax.map(fn, angles, batch_size=int(batch_size))


def broadcast_image(image: Array, n: int) -> Array:
    """One image repeated for `n` lights, ``(n, ...)`` (a shift-invariant model's batch)."""
    return jnp.broadcast_to(image, (n, *image.shape))


def wavelength_tuple(wavelengths_nm: ArrayLike) -> tuple[float, ...]:
    """Concrete wavelengths as a tuple of floats (for the interface and file headers)."""
    return tuple(float(w) for w in np.asarray(wavelengths_nm, dtype=float).reshape(-1))
