"""A glare PSF as a renderer's convolution kernel: Blender's compositor and Unreal's bloom.

`invglare render` spreads every pixel of a frame with the PSF
(`invglare.render.convolve.convolve_psf`: pixel ``i`` sends ``psf[c + d]`` to the pixel
``d`` away, ``c`` the PSF's centre). A renderer that convolves a frame with a kernel image
gives the same result only when the kernel is laid out the way that renderer reads it.
This module lays a PSF (already at the frame's pixel scale, energy per pixel) out for each
target; `invglare export-kernel` (`invglare.commands.export_kernel`) writes the result
as a linear float32 OpenEXR.

**Blender** (compositor, *Glare* node of type *Kernel* and the *Convolve* node). Read from
Blender's source, `compositor/algorithms/intern/convolve.cc` (the routine both nodes call)
and `nodes/composite/nodes/node_composite_glare.cc` / `node_composite_convolve.cc`:

- the kernel's centre is the pixel ``size // 2`` on each axis. Blender keeps images bottom
  row first, so a file row ``r`` is Blender row ``size - 1 - r``: only an **odd** size puts
  the file's centre row on Blender's centre row (an even one shifts the glare by a pixel);
- the kernel is written into the FFT buffer at ``centre - offset``, so Blender *gathers*
  (``out[x] = sum_s K[s] in[x + s - c]``, the manual's "the kernel is centred over each
  pixel ... multiplied by the corresponding kernel value"), which is the spread of the
  kernel **point-reflected**. `blender_kernel` therefore stores the PSF rotated by
  180 deg (a no-op for the point-symmetric PSF of any real aperture in the Fraunhofer
  regime; it matters for Fresnel, position-dependent or synthetic PSFs);
- image and kernel are zero-padded to ``image + max(kernel, image) - 1``: no wrap-around,
  as `convolve_psf(pad=True)`;
- **normalisation**: with a *Color* kernel every channel is divided by its own sum (a
  *Float* kernel by its one sum). The *Glare* node always normalises
  (``convolve(..., true)``), the *Convolve* node unless its *Normalize Kernel* input is
  off (default on). Per-channel normalisation makes each channel of the kernel carry unit
  energy, so a **coloured kernel loses its tint**: a white light gets a white glare,
  whatever the PSF's colour (a spectral PSF whose red holds less energy in the field than
  its blue becomes neutral). Three ways to keep it: the *Convolve* node with *Normalize
  Kernel* off (the file's absolute values: exactly `invglare render`); or the *Glare*
  node's *Tint* set to the kernel's channel energies (`channel_energy`, printed by
  the command; a linear colour, whose values may exceed 1 for an RGB PSF, with *Strength*
  1); or a *Mix* (multiply) by that colour after a normalising *Convolve*;
- the *Glare* node convolves its *highlights* (each pixel's HSV value minus *Threshold*;
  with Threshold 0 the image itself), at a quarter or half of the resolution unless
  *Quality* is *High* (default *Medium*), and its *Image* output adds the glare to the
  input (``input + glare * tint * strength``), counting the unscattered core twice: take
  its *Glare* output, or use the *Convolve* node, to get `invglare render`'s frame.

**Unreal Engine** (post-process *Bloom*, method *Convolution*). From Unreal's
`FConvolutionBloomSettings` reference (Engine/Scene.h) and Epic's notes on it:

- *Convolution Kernel*: "Texture to replace default convolution bloom kernel", an HDR
  texture (EXR); Epic's staff on the forum (4.16, "The new FFT convolution bloom"): "the
  hottest (brightest) part of the image should be much brighter than any other part ...
  by a lot" and the system "expects the hottest (brightest) point of the image to be at
  the center". D. Hill (Epic, "Convolution (FFT) Bloom", 2017) models bloom as weak
  scattering, every point scattered the same, the kernel's centre pixel (about 10 000
  times brighter than the rest in Epic's own kernel) being the light that stays focused;
- *Convolution Center*: "The UV location of the center of the kernel. Should be very
  close to (.5,.5)": an odd size puts the centre pixel's centre at UV (0.5, 0.5) exactly;
- *Convolution Scale*: "Relative size of the convolution kernel image compared to the
  minor axis of the viewport": one kernel texel per screen pixel is
  ``size_px / minor_axis_px`` (`unreal_convolution_scale`), with the kernel made at
  the screen's pixel scale (`viewport_pixel_scale_deg`);
- *Scatter Dispersion* (5.0+): "Intensity multiplier on the scatter dispersion energy of
  the kernel. 1.0 means exactly use the same energy as the kernel scatter dispersion": the
  engine reads the scattered energy *relative to the kernel's centre*. Hence the exported
  kernel keeps the PSF's **unclipped** centre pixel and its true core-to-halo energy ratio
  (`centre_fraction`); a clipped or boosted centre would change how much light
  scatters. The reference pages found do not state how the engine normalises the
  kernel's total; the tests model it as a unit-sum normalisation (what a scatter model in
  which only ratios within the kernel matter implies), under which the bloom is
  `invglare render`'s frame divided by the energy the kernel holds (set *Intensity* to
  `channel_energy`'s luminance to keep the absolute level);
- *Convolution Buffer* (``BufferScale``): the padding that stops the bloom wrapping
  across the screen.

Every function here is pure (`jax.numpy` on arrays of static shape): they work under
`jit`; the checks on sizes and targets run in Python before any array work.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from invglare._core.checks import as_float
from invglare._core.colour import rec709_luminance
from invglare.errors import ConfigError, InputDataError, PhysicsRangeError

__all__ = [
    "TARGETS",
    "blender_kernel",
    "centre_fraction",
    "centred",
    "channel_energy",
    "check_kernel_request",
    "kernel_for",
    "luminance_energy",
    "peak_offset_px",
    "rgb",
    "unreal_convolution_scale",
    "unreal_kernel",
    "viewport_pixel_scale_deg",
]

#: The renderers a kernel can be laid out for.
TARGETS = ("blender", "unreal")

Kernel = Float[Array, "n n 3"]


def check_kernel_request(target: str, npix: int | None = None) -> str:
    """Validate a kernel request before any work: the target and an odd size.

    **Arguments:**

    - `target`: one of `TARGETS` (case-insensitive).
    - `npix`: the kernel's size in pixels, odd and >= 3, or None (the PSF's own size,
      made odd).

    **Returns:** the target in lower case.

    **Raises:** `ConfigError` naming the value: an unknown target (listing the known
    ones), an even size (the centre pixel would not be the middle one; say why), a size
    below 3 or not an integer.

    **Example:**

    ```python
    check_kernel_request("Blender", 513)   # "blender"
    ```
    """
    name = str(target).lower()
    if name not in TARGETS:
        raise ConfigError(f"unknown kernel target {target!r}; choose one of {', '.join(TARGETS)}")
    if npix is None:
        return name
    if isinstance(npix, bool) or not isinstance(npix, int):
        raise ConfigError(f"kernel size must be an odd integer >= 3, got {npix!r}")
    if npix < 3:
        raise ConfigError(f"kernel size must be an odd integer >= 3, got {npix}")
    if npix % 2 == 0:
        raise ConfigError(
            f"kernel size must be odd, got {npix}: both renderers take pixel size // 2 as the "
            f"centre, which only an odd size puts in the middle (try {npix + 1} or {npix - 1})"
        )
    return name


def _odd(n: int) -> int:
    return n + 1 - n % 2


def centred(psf: Float[ArrayLike, "h w *c"], npix: int) -> Float[Array, "npix npix *c"]:
    """Crop or zero-pad a PSF to `npix` x `npix` keeping its centre pixel in the middle.

    The PSF's centre is ``(h // 2, w // 2)`` (the convention of
    `invglare.render.convolve.convolve_psf`); it lands on ``(npix // 2, npix // 2)``.
    Energy outside the new window is dropped.

    **Example:**

    ```python
    centred(jnp.ones((4, 4)), 5).shape   # (5, 5), the old (2, 2) now at (2, 2)
    ```
    """
    psf = as_float(psf)
    h, w = psf.shape[:2]
    out = jnp.zeros((npix, npix, *psf.shape[2:]), psf.dtype)
    # Source and destination ranges along each axis, offsets measured from the centres.
    (sy0, sy1, dy0), (sx0, sx1, dx0) = (_overlap(h, npix), _overlap(w, npix))
    return out.at[dy0 : dy0 + sy1 - sy0, dx0 : dx0 + sx1 - sx0].set(psf[sy0:sy1, sx0:sx1])


def _overlap(n_src: int, n_dst: int) -> tuple[int, int, int]:
    """Source slice ``[s0, s1)`` and destination start of centre-aligned axes."""
    back = min(n_src // 2, n_dst // 2)
    forward = min(n_src - 1 - n_src // 2, n_dst - 1 - n_dst // 2)
    return n_src // 2 - back, n_src // 2 + forward + 1, n_dst // 2 - back


def rgb(psf: Float[ArrayLike, "h w *c"]) -> Float[Array, "h w 3"]:
    """A mono PSF as three equal channels; an RGB PSF unchanged.

    Both renderers read kernels as colour images; three equal channels are the same kernel
    as a Float (Blender's colour-to-float conversion of a grey pixel is its value).
    """
    psf = as_float(psf)
    if psf.ndim == 2:
        return jnp.repeat(psf[..., None], 3, axis=-1)
    if psf.ndim == 3 and psf.shape[2] == 3:
        return psf
    if psf.ndim == 3 and psf.shape[2] == 1:
        return jnp.repeat(psf, 3, axis=-1)
    raise InputDataError(f"a PSF must have shape (h, w), (h, w, 1) or (h, w, 3); got {psf.shape}")


def _prepared(psf: ArrayLike, npix: int | None) -> Kernel:
    psf = as_float(psf)
    if psf.ndim not in (2, 3) or min(psf.shape[:2]) < 1:
        raise InputDataError(f"a PSF must have shape (h, w) or (h, w, C); got {psf.shape}")
    if npix is None:
        npix = max(3, _odd(max(psf.shape[:2])))
    else:
        check_kernel_request("blender", npix)
    return centred(rgb(psf), npix)


def blender_kernel(psf: Float[ArrayLike, "h w *c"], npix: int | None = None) -> Kernel:
    """The PSF as a kernel for Blender's *Glare* (Kernel) and *Convolve* nodes.

    Odd size, centre on pixel ``npix // 2``, RGB, the PSF's absolute values (energy per
    pixel), **rotated by 180 deg** because Blender gathers with its kernel (see the module
    docstring): Blender's *Convolve* node with *Normalize Kernel* off then gives exactly
    ``convolve_psf(frame, psf)``; with normalisation on (and in the *Glare* node), each
    channel ``c`` becomes ``psf_c / channel_energy(kernel)[c]``.

    **Arguments:**

    - `psf`: `(h, w)` or `(h, w, 3)` energy per pixel at the frame's pixel scale, centre
      at `(h // 2, w // 2)`.
    - `npix`: odd kernel size (crops or pads about the centre); None: the PSF's size, made
      odd.

    **Returns:** `(npix, npix, 3)`, the PSF's dtype.

    **Example:**

    ```python
    k = blender_kernel(psf, 513)   # write with write_exr(path, np.asarray(k), ...)
    ```
    """
    return _prepared(psf, npix)[::-1, ::-1]


def unreal_kernel(psf: Float[ArrayLike, "h w *c"], npix: int | None = None) -> Kernel:
    """The PSF as a kernel texture for Unreal's convolution bloom.

    Odd size (the centre pixel's centre is UV (0.5, 0.5) exactly), RGB, the PSF's absolute
    values: the centre pixel unclipped, so the ratio of the light that stays focused to
    the light that scatters is the model's (`centre_fraction`). Not reflected: an
    FFT convolution spreads its kernel as `convolve_psf` does (only a PSF without point
    symmetry would tell). Check `peak_offset_px` before use: the engine expects the
    brightest pixel at the centre.

    **Arguments:** as `blender_kernel`.

    **Returns:** `(npix, npix, 3)`, the PSF's dtype.
    """
    return _prepared(psf, npix)


def kernel_for(target: str, psf: Float[ArrayLike, "h w *c"], npix: int | None = None) -> Kernel:
    """`blender_kernel` or `unreal_kernel` by name (validated first)."""
    name = check_kernel_request(target, npix)
    return blender_kernel(psf, npix) if name == "blender" else unreal_kernel(psf, npix)


def channel_energy(kernel: Float[ArrayLike, "n n 3"]) -> Float[Array, " 3"]:
    """Each channel's sum: the fraction of the light the kernel holds, per channel.

    It is what Blender divides each channel by when it normalises, so it is also the
    *Tint* that gives a normalising *Glare* node back the kernel's colour and level.
    """
    return jnp.sum(as_float(kernel), axis=(0, 1))


def luminance_energy(kernel: Float[ArrayLike, "n n 3"]) -> Float[Array, ""]:
    """The Rec. 709 luminance of `channel_energy` (one number for a whole kernel)."""
    return rec709_luminance(channel_energy(kernel))


def centre_fraction(kernel: Float[ArrayLike, "n n 3"]) -> Float[Array, " 3"]:
    """The centre pixel's share of each channel's energy (the light that stays focused).

    ``f / (1 - f)`` is the core-to-halo energy ratio a scatter model (Unreal's bloom)
    reads from the kernel.
    """
    kernel = as_float(kernel)
    c = kernel.shape[0] // 2
    total = channel_energy(kernel)
    return kernel[c, c] / jnp.where(total > 0, total, 1.0)


def peak_offset_px(kernel: Float[ArrayLike, "n n 3"]) -> tuple[int, int]:
    """``(rows, columns)`` from the centre to the brightest pixel (luminance); (0, 0) ideal.

    Concrete kernels only (it returns Python ints).
    """
    kernel = as_float(kernel)
    lum = rec709_luminance(kernel)
    row, col = divmod(int(jnp.argmax(lum)), kernel.shape[1])
    return row - kernel.shape[0] // 2, col - kernel.shape[1] // 2


def viewport_pixel_scale_deg(fov_deg: float, width_px: int) -> float:
    """Degrees per pixel at the centre of a pinhole camera's frame.

    A horizontal field of view `fov_deg` over `width_px` pixels puts the focal length at
    ``f = (width_px / 2) / tan(fov / 2)`` pixels; the centre pixel subtends ``1 / f`` rad
    (paraxially; pixels towards the edges subtend less, as ``cos²`` of their angle).

    **Raises:** `PhysicsRangeError` for a field of view outside (0, 180) deg or a width
    below 1.

    **Example:**

    ```python
    viewport_pixel_scale_deg(90.0, 1920)   # 0.0597 deg/px
    ```
    """
    fov = float(fov_deg)
    if not (math.isfinite(fov) and 0.0 < fov < 180.0):
        raise PhysicsRangeError(f"field of view must be in (0, 180) deg, got {fov_deg!r}")
    if int(width_px) < 1:
        raise PhysicsRangeError(f"viewport width must be >= 1 px, got {width_px!r}")
    return math.degrees(2.0 * math.tan(math.radians(fov) / 2.0) / int(width_px))


def unreal_convolution_scale(npix: int, viewport_px: tuple[int, int]) -> float:
    """Unreal's *Convolution Scale* for one kernel texel per screen pixel.

    The setting is "relative size of the convolution kernel image compared to the minor
    axis of the viewport", so a kernel of `npix` texels spans ``npix`` screen pixels at
    ``npix / min(width, height)``.

    **Example:**

    ```python
    unreal_convolution_scale(1079, (1920, 1080))   # 0.99907
    ```
    """
    width, height = (int(v) for v in viewport_px)
    if min(width, height) < 1:
        raise ConfigError(f"viewport must be at least 1 x 1 px, got {width} x {height}")
    return int(npix) / min(width, height)
