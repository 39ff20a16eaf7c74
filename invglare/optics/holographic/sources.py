"""Point sources from a frame and its depth buffer (Novosad & Ziegler, sec. 2.3.1).

Every pixel of the input frame becomes one point source:

- **where**: the pixel's direction from the view frustum (perspective pixels are evenly
  spaced in ``tan(theta)``) times its depth; a depth buffer holds planar depth ``z``
  (along the view axis), a ray distance, or a normalised z-buffer value decoded with the
  near and far planes (:class:`Frustum`); without a depth buffer one constant depth is
  used, as the paper does for its HDR example;
- **how bright**: the amplitude is ``sqrt(value)``, so that intensities add up to the
  pixel values (the paper gives bright HDR pixels large amplitudes; the square root is
  what makes the speckle-free image the frame convolved with the eye's PSF). The 1/r of
  eq. 2.2 is compensated: a pixel already holds what reaches the eye from its direction;
- **which phase**: random per iteration (:func:`random_phasors`).

**Layouts.** The output image is an ``N x N`` grid of directions (row 0 at the top, as
images are stored; centre pixel ``N // 2``); a frame of ``H x W`` pixels is placed at its
centre, each input pixel on every `step`-th output pixel (``step > 1``: fewer sources
than output pixels, the paper's decoupled input resolution). The propagation works in
the FFT's own (unshifted) layout: :func:`image_to_bins` maps the output grid to FFT bins
and :func:`bins_to_image` back. A source looking along ``t = (tan theta_x, tan
theta_y)`` sends light *travelling* along ``-t``: spatial frequency ``-t / lambda`` at the
eye. The mapping includes that mirror, so the returned image is upright and not mirrored
(the way the frame looks), and the layers' rasters are in the eye's own frame (x to the
right, y up, seen from behind the eye).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Complex, Float, Inexact, Int, Key

from invglare.errors import ConfigError, InputDataError, PhysicsRangeError

__all__ = [
    "DEPTH_ENCODINGS",
    "PHASES",
    "Frustum",
    "bins_to_image",
    "check_depth_buffer",
    "check_frame",
    "crop_frame",
    "decode_depth",
    "directions",
    "image_to_bins",
    "layer_vergences",
    "place_frame",
    "random_phasors",
    "reproject",
    "source_amplitudes",
]

#: How a depth buffer's values are read; see :func:`decode_depth`.
DEPTH_ENCODINGS = ("linear", "distance", "normalised", "linear01")
#: Random phases per iteration: uniform on [0, 2 pi), or one of the four quarter turns.
PHASES = ("uniform", "quaternary")


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


class Frustum(eqx.Module):
    """The view frustum of a frame: how its depth buffer turns into distances (static).

    **Fields:**

    - `fov_x_deg`: horizontal field of view (deg) of the frame, or None: then the frame
      is taken to be at the eye model's pixel scale (times its input step). When given,
      it is checked against the model.
    - `near_mm`, `far_mm`: the near and far planes (mm), needed by the normalised
      encodings.
    - `depth_encoding`: ``"linear"`` (planar depth ``z`` along the view axis, the usual
      ``Z`` channel), ``"distance"`` (distance along each pixel's ray), ``"normalised"``
      (a Direct3D-style z-buffer in ``[0, 1]``, hyperbolic: ``0`` at near, ``1`` at far),
      ``"linear01"`` (``z = near + d (far - near)``).
    - `depth_unit_mm`: mm per unit of a ``"linear"`` / ``"distance"`` value (1000: metres).
    """

    fov_x_deg: float | None = eqx.field(static=True, default=None)
    near_mm: float | None = eqx.field(static=True, default=None)
    far_mm: float | None = eqx.field(static=True, default=None)
    depth_encoding: str = eqx.field(static=True, default="linear")
    depth_unit_mm: float = eqx.field(static=True, default=1000.0)

    def __check_init__(self):
        if self.depth_encoding not in DEPTH_ENCODINGS:
            raise ConfigError(
                f"depth_encoding = {self.depth_encoding!r} is not one of "
                f"{', '.join(DEPTH_ENCODINGS)}"
            )
        if self.fov_x_deg is not None and not (0.0 < self.fov_x_deg < 180.0):
            raise PhysicsRangeError(f"fov_x_deg must be in (0, 180) deg, got {self.fov_x_deg!r}")
        if not (math.isfinite(self.depth_unit_mm) and self.depth_unit_mm > 0):
            raise PhysicsRangeError(f"depth_unit_mm must be > 0, got {self.depth_unit_mm!r}")
        for name in ("near_mm", "far_mm"):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise PhysicsRangeError(f"frustum {name} must be > 0, got {value!r} mm")
        if self.depth_encoding in ("normalised", "linear01"):
            if self.near_mm is None or self.far_mm is None or not math.isfinite(self.far_mm):
                raise ConfigError(
                    f"depth_encoding = {self.depth_encoding!r} needs finite near_mm and far_mm"
                )
        if self.near_mm is not None and self.far_mm is not None and self.near_mm >= self.far_mm:
            raise PhysicsRangeError(
                f"frustum near_mm ({self.near_mm:g}) must be below far_mm ({self.far_mm:g})"
            )

    def pixel_scale_rad(self, width_px: int) -> float | None:
        """Tangent step of one frame pixel, ``2 tan(fov / 2) / width`` (None without a fov)."""
        if self.fov_x_deg is None:
            return None
        return 2.0 * math.tan(math.radians(self.fov_x_deg) / 2.0) / width_px


# ------------------------------------------------------------------------------ checks


def check_frame(frame: ArrayLike) -> np.ndarray | None:
    """Refuse a frame that is not ``(H, W)`` / ``(H, W, C)``, non-finite or negative.

    Traced frames are not checked (validate before `jit`). Returns the concrete frame.
    """
    if not _is_concrete(frame):
        return None
    arr = np.asarray(frame)
    if arr.ndim not in (2, 3) or min(arr.shape[:2]) < 1:
        raise InputDataError(f"frame must have shape (H, W) or (H, W, C), got {arr.shape}")
    bad = ~np.isfinite(arr)
    if bad.any():
        where = tuple(int(i) for i in np.argwhere(bad)[0])
        raise InputDataError(f"frame holds a non-finite value {float(arr[where])} at {where}")
    if (arr < 0).any():
        where = tuple(int(i) for i in np.argwhere(arr < 0)[0])
        raise InputDataError(
            f"frame holds a negative value {float(arr[where]):g} at {where}; frames are "
            "linear radiances (>= 0)"
        )
    return arr


def check_depth_buffer(
    depth: ArrayLike, frame_shape: tuple[int, ...], frustum: Frustum
) -> np.ndarray | None:
    """Refuse a depth buffer of another size than the frame, or with bad values.

    **Raises:** `InputDataError` naming both shapes for a size mismatch, and the first bad
    pixel for a non-finite value, a negative (or zero) depth, or a normalised value
    outside ``[0, 1]``. Traced buffers are not checked.
    """
    if not _is_concrete(depth):
        return None
    arr = np.asarray(depth)
    if arr.ndim == 3 and arr.shape[-1] == 1:
        arr = arr[..., 0]
    if arr.shape != tuple(frame_shape[:2]):
        raise InputDataError(
            f"depth buffer has shape {arr.shape} but the frame is {tuple(frame_shape[:2])}; "
            "they must be the same size (one depth per pixel)"
        )
    bad = ~np.isfinite(arr)
    if bad.any():
        where = tuple(int(i) for i in np.argwhere(bad)[0])
        raise InputDataError(
            f"depth buffer holds a non-finite value {float(arr[where])} at {where}"
        )
    if frustum.depth_encoding in ("normalised", "linear01"):
        out = (arr < 0) | (arr > 1)
        if out.any():
            where = tuple(int(i) for i in np.argwhere(out)[0])
            raise InputDataError(
                f"depth buffer value {float(arr[where]):g} at {where} is outside [0, 1], the "
                f"range of depth_encoding = {frustum.depth_encoding!r}"
            )
    elif (arr <= 0).any():
        where = tuple(int(i) for i in np.argwhere(arr <= 0)[0])
        raise InputDataError(
            f"depth buffer holds the depth {float(arr[where]):g} at {where}; depths must be "
            "> 0 (in front of the eye)"
        )
    return arr


# ------------------------------------------------------------------------------ geometry


def directions(npix: int, pixel_scale_rad: float, dtype=None) -> tuple[Array, Array]:
    """``(tan theta_y, tan theta_x)`` of every output pixel, ``(N, N)`` each (y up, row 0 top)."""
    dtype = jnp.result_type(float) if dtype is None else dtype
    k = jnp.arange(npix, dtype=dtype) - npix // 2
    tx = jnp.broadcast_to(k[None, :] * pixel_scale_rad, (npix, npix))
    ty = jnp.broadcast_to(-k[:, None] * pixel_scale_rad, (npix, npix))
    return ty, tx


def decode_depth(
    depth: Float[ArrayLike, "*shape"],
    frustum: Frustum,
    tangents: tuple[ArrayLike, ArrayLike] | None = None,
) -> Float[Array, "*shape"]:
    """Planar depth ``z`` (mm) from depth-buffer values (see :class:`Frustum`).

    `tangents` (``tan theta_y, tan theta_x`` of each pixel) are needed by the
    ``"distance"`` encoding: ``z = distance / sqrt(1 + tan_x**2 + tan_y**2)``.
    """
    d = jnp.asarray(depth)
    if not jnp.issubdtype(d.dtype, jnp.floating):
        d = d.astype(jnp.result_type(float))
    enc = frustum.depth_encoding
    if enc == "linear":
        return d * frustum.depth_unit_mm
    if enc == "distance":
        if tangents is None:
            raise ConfigError("depth_encoding = 'distance' needs the pixels' directions")
        ty, tx = tangents
        return d * frustum.depth_unit_mm / jnp.sqrt(1.0 + tx * tx + ty * ty)
    near, far = frustum.near_mm, frustum.far_mm
    if enc == "linear01":
        return near + d * (far - near)
    # Direct3D: d = far (z - near) / (z (far - near)), so z = near far / (far - d (far - near)).
    return near * far / (far - d * (far - near))


def reproject(depth_mm: Float[ArrayLike, "n n"], pixel_scale_rad: float) -> Float[Array, "n n 3"]:
    """World positions (mm; x right, y up, z forward from the pupil) of the output grid's pixels.

    Pixel ``(row, col)`` looks along ``(tan_x, tan_y, 1)``; at planar depth ``z`` it sits at
    ``z (tan_x, tan_y, 1)``: the paper's reprojection through the view frustum.
    """
    z = jnp.asarray(depth_mm)
    ty, tx = directions(z.shape[-1], pixel_scale_rad, z.dtype)
    return jnp.stack([z * tx, z * ty, z], axis=-1)


# ------------------------------------------------------------------------------ layouts


def _row_index(n: int) -> np.ndarray:
    # image row r (direction tan_y = -(r - n//2) dt) -> frequency row (r - n//2) mod n.
    return (np.arange(n) + n // 2) % n


def _col_index(n: int) -> np.ndarray:
    # image column c (tan_x = (c - n//2) dt) -> frequency column (n//2 - c) mod n; an involution.
    return (n // 2 - np.arange(n)) % n


def image_to_bins(x: Inexact[Array, "*c n n"]) -> Inexact[Array, "*c n n"]:
    """Output-grid layout (centred, row 0 at the top) to FFT-bin layout (last two axes)."""
    n = x.shape[-1]
    return x[..., _row_index(n)[:, None], _col_index(n)[None, :]]


def bins_to_image(x: Inexact[Array, "*c n n"]) -> Inexact[Array, "*c n n"]:
    """FFT-bin layout back to the output grid (the inverse of :func:`image_to_bins`)."""
    n = x.shape[-1]
    rows = (np.arange(n) - n // 2) % n
    return x[..., rows[:, None], _col_index(n)[None, :]]


def place_frame(frame_cf: Float[Array, "c h w"], npix: int, step: int = 1) -> Float[Array, "c n n"]:
    """Put a channels-first frame at the centre of the ``N x N`` output grid, one pixel per `step`.

    Input pixel ``(i, j)`` lands on output pixel ``(r0 + step i + step // 2, c0 + step j +
    step // 2)`` with ``r0 = (N - step H) // 2``; for an even `step` that is half an output
    pixel from the input pixel's centre.
    """
    c, h, w = frame_cf.shape
    if step * h > npix or step * w > npix:
        raise InputDataError(
            f"a {h} x {w} frame with input step {step} needs a grid of at least "
            f"{step * max(h, w)} px; the eye's grid is {npix} px"
        )
    r0, c0 = (npix - step * h) // 2, (npix - step * w) // 2
    out = jnp.zeros((c, npix, npix), frame_cf.dtype)
    rows = slice(r0 + step // 2, r0 + step // 2 + step * h, step)
    cols = slice(c0 + step // 2, c0 + step // 2 + step * w, step)
    return out.at[:, rows, cols].set(frame_cf)


def crop_frame(image_cf: Float[Array, "c n n"], shape: tuple[int, int], step: int = 1):
    """The output pixels that a ``shape`` frame placed by :func:`place_frame` covers."""
    h, w = shape
    n = image_cf.shape[-1]
    r0, c0 = (n - step * h) // 2, (n - step * w) // 2
    return image_cf[..., r0 : r0 + step * h, c0 : c0 + step * w]


def source_amplitudes(frame_cf: Float[Array, "c h w"], step: int = 1) -> Float[Array, "c h w"]:
    """Amplitudes ``step * sqrt(value)``: each source carries the light of ``step**2`` pixels."""
    return step * jnp.sqrt(jnp.maximum(frame_cf, 0.0))


def random_phasors(
    key: Key[Array, ""], shape: tuple[int, ...], kind: str = "uniform", dtype=jnp.complex64
) -> Complex[Array, "*shape"]:
    """Unit phasors ``exp(i phi)`` with independent random phases, one per source.

    ``"uniform"``: ``phi`` uniform over ``[0, 2 pi)`` (the paper's choice), drawn as one of
    ``2^16`` equally spaced phases, two from each random 32-bit word: half the random bits
    of a float draw, and every moment ``E[e^{i k phi}]``, ``0 < |k| < 2^16``, is zero as
    for the continuous uniform. ``"quaternary"``: ``phi`` one of
    ``0, pi/2, pi, 3 pi/2`` with equal odds, drawn from two random bits and needing no
    trigonometry. Both give ``E[e^{i(phi_j - phi_k)}] = 0`` for ``j != k`` and the same
    fourth moments of the field (``E[e^{2 i phi}] = 0`` for both), so the iteration average
    has the same expectation, the speckle-free image, and the same speckle contrast per
    iteration; binary phases (``0, pi``) would not (``E[e^{2 i phi}] = 1``).
    """
    if kind not in PHASES:
        raise ConfigError(f"phases = {kind!r} is not one of {', '.join(PHASES)}")
    real_dtype = jnp.finfo(dtype).dtype
    if kind == "uniform":
        size = math.prod(shape)
        words = jax.random.bits(key, ((size + 1) // 2,), jnp.uint32)
        levels = jnp.concatenate([words & 0xFFFF, words >> 16])[:size].reshape(shape)
        phi = (levels.astype(real_dtype) + 0.5) * (2.0 * math.pi / 65536.0)
        return jax.lax.complex(jnp.cos(phi), jnp.sin(phi)).astype(dtype)
    bits = jax.random.bits(key, shape, jnp.uint8)
    re = jnp.where(bits & 1, 0.0, jnp.where(bits & 2, -1.0, 1.0)).astype(real_dtype)
    im = jnp.where(bits & 1, jnp.where(bits & 2, -1.0, 1.0), 0.0).astype(real_dtype)
    return jax.lax.complex(re, im).astype(dtype)


# ------------------------------------------------------------------------------ depth layers


def layer_vergences(
    vergence_per_mm: Float[Array, "n n"],
    weight: Float[Array, "n n"],
    n_layers: int,
) -> tuple[Float[Array, " l"], Int[Array, "n n"]]:
    """Depth layers evenly spaced in vergence over the sources' range, and each source's layer.

    **Arguments:**

    - `vergence_per_mm`: ``1 / z`` of every source (1/mm).
    - `weight`: where sources are (> 0); empty bins do not widen the range.
    - `n_layers`: number of layers (static; see
      :func:`~invglare.optics.holographic.sampling.depth_layers_needed`).

    **Returns:** the layers' vergences (the centres of ``n_layers`` equal bins from the
    smallest to the largest vergence) and the index of each source's nearest layer. One
    layer puts every source at the mid-range vergence (exact for one constant depth).
    """
    present = weight > 0
    big = jnp.finfo(vergence_per_mm.dtype).max
    lo = jnp.min(jnp.where(present, vergence_per_mm, big))
    hi = jnp.max(jnp.where(present, vergence_per_mm, -big))
    lo, hi = jnp.minimum(lo, hi), jnp.maximum(lo, hi)  # no source at all: lo = hi
    step = (hi - lo) / n_layers
    centres = lo + (jnp.arange(n_layers, dtype=vergence_per_mm.dtype) + 0.5) * step
    safe = jnp.where(step > 0, step, 1.0)
    index = jnp.clip(jnp.floor((vergence_per_mm - lo) / safe), 0, n_layers - 1).astype(jnp.int32)
    return centres, index
