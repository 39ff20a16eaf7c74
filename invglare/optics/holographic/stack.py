"""The layer stack: sources -> base layer -> thin layers -> lens -> retina, and its averages.

One colour channel's stack is a :class:`ChannelStack` of arrays on its aperture grid: the
sources at their FFT bins (bin 0 first), the planes' arrays centred (the axis at sample
``m // 2``), transfer functions in FFT layout. Nothing is shifted per iteration: the bins
are multiplied by the centring ramp ``exp(-2 pi i k (m // 2) / N)`` instead, which moves the
inverse FFT's samples so that the centred ``m x m`` window is ``[0, m)^2``; the retinal
field then carries the matching ramp, which its intensity does not see.

1. base layer: ``u = sum_l front_l * ifft2(C * [layer == l])`` (ortho-normalised), where
   ``C`` holds the sources' complex amplitudes at their FFT bins and ``front_l`` is the
   curvature of depth layer ``l`` times the transmission of the first plane
   (:mod:`invglare.optics.holographic.base_layer`);
2. for each further plane: ``u = ifft2(fft2(u) * kernel) * transmission``, the
   band-limited angular spectrum between parallel planes
   (:func:`~invglare.optics.holographic.layers.propagation_kernel`), the last
   transmission being the pupil times the lens;
3. retina: ``fft2(u)`` (ortho). The lens focuses the eye's far point on the retina, so the
   Fresnel propagation to the retina is a Fourier transform whose frequencies are the
   output directions; the lens layer holds only the *accommodation* ``A``,
   ``exp(-i pi A r^2 / lambda)``, and the retinal image of bin ``k`` is output pixel ``k``.

``gain * |fft2(u)|^2`` is the retinal image, with ``gain = 1 / (transmitted fraction of the
clear pupil)``: a point source gives a PSF of unit energy through a clear pupil, so the
image keeps the frame's brightness whatever the pupil's size (lashes in front of it still
take their share).

**Iterations** (:func:`iterate_intensity`, sec. 2.3): new random phases for all sources,
propagate, average the intensities. Iterations run in chunks (`vmap` inside a chunk,
`lax.scan` over chunks) sized to a memory budget (:func:`iteration_bytes`).

**The speckle-free limit** (:func:`speckle_free`): the average over infinitely many
iterations, computed directly. Random phases make the sources mutually incoherent:
``E|sum_j C_j e^{i phi_j} h_j|^2 = sum_j |C_j|^2 |h_j|^2`` with ``h_j`` the field of source
``j`` alone. When every thin layer sits in the pupil plane, ``h_j`` is ``h_0`` shifted to bin
``j`` (exactly, on the periodic grid), and the limit is ``|C|^2`` circularly convolved with
one PSF per depth layer: exact. Layers in front of the pupil (lashes, tear film,
spectacles) are met by each direction at a different place (the light of direction
``theta`` crosses a plane ``d`` in front of the pupil ``d tan(theta)`` off the axis), so
``|h_j|^2`` changes with ``j``; the limit then uses exact PSFs at the centres of ``K x K``
tiles of the output, blended bilinearly between them: exact at the tile centres, and
``K = 1`` is the on-axis PSF everywhere.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Complex, Float, Int, Key

from invglare.errors import ConfigError
from invglare.optics.holographic.sources import random_phasors

__all__ = [
    "ChannelStack",
    "iterate_intensity",
    "iteration_bytes",
    "point_response",
    "speckle_contrast",
    "speckle_free",
    "stack_bytes",
    "stack_field",
    "tile_weights",
]


class ChannelStack(eqx.Module):
    """One wavelength's layer stack, centred arrays (a leading channel axis when stacked).

    **Fields:**

    - `front`: ``(L, m, m)`` per depth layer, its curvature times the first plane's
      transmission (the pupil and lens too when nothing is in front of the pupil).
    - `kernels`: transfer functions to each further plane, ``(m, m)``, FFT layout.
    - `transmissions`: the transmission at each further plane (the last is the pupil
      times the lens), ``(m, m)``.
    - `gain`: ``1 / (transmitted fraction of the clear pupil)`` over the output grid.
    - `npix_out`: the output grid ``N`` (static); ``m < N`` is a *cropped* stack.

    **Cropped stacks.** Only the light that reaches the pupil matters, and between the base
    plane and the pupil it stays within ``d tan(theta_max)`` of where it will pass: a disk of
    the pupil's radius plus that walk, usually a fraction of the window. A cropped stack runs
    the layers on the central ``m x m`` samples of the same pitch: the base layer's inverse FFT
    is evaluated only there (above :data:`WHOLE_FFT_MAX_NPIX`, rows, then the kept columns: a
    pruned transform), the layers' transfer functions are ``m``-point ones, and the retina's FFT
    zero-pads the pupil field back to ``N`` (pruned again). The fronts carry a smooth taper over
    the crop's outer margin so that the cropped field has no edge to diffract from; the pupil's
    light never comes from there, so the pupil field is that of the full grid (the tests compare
    the two). Cost per channel and iteration: two pruned size-``N`` FFTs (``(1 + m / N) / 2`` of
    a whole one each) and ``m``-point ones for the layers, instead of ``2 + 2 x planes``
    size-``N`` FFTs.
    """

    front: Complex[Array, "l m m"]
    kernels: tuple[Complex[Array, "m m"], ...]
    transmissions: tuple[Complex[Array, "m m"], ...]
    gain: Float[Array, ""]
    npix_out: int = eqx.field(static=True, default=0)

    @property
    def n_layers(self) -> int:
        return self.front.shape[-3]

    @property
    def npix(self) -> int:
        """The output grid ``N`` (the sources' bins and the retina's pixels)."""
        return self.npix_out or self.front.shape[-1]

    @property
    def crop(self) -> int:
        """The layers' grid ``m`` (``N`` when not cropped)."""
        return self.front.shape[-1]


def _centring_ramp(n: int, shift: int, dtype) -> Complex[Array, " n"]:
    """``exp(-2 pi i k shift / n)`` over the FFT bins ``k``: multiplied into the bins along
    an axis, it moves the inverse FFT's samples by `shift` (the shift theorem)."""
    turns = (np.arange(n) * shift) % n  # exact integers: the phase stays in [0, 2 pi)
    phase = jnp.asarray(turns, jnp.finfo(dtype).dtype) * (-2.0 * np.pi / n)
    return jax.lax.complex(jnp.cos(phase), jnp.sin(phase)).astype(dtype)


#: Up to this grid the base layer's window comes from one whole 2-D inverse FFT, above it
#: from the pruned one: at 256^2 (crop 128, 8 depth layers, RGB, 16 iterations) the whole
#: transform took 0.125-0.136 s against 0.130-0.152 s, at 512^2 (crop 240, 64 iterations)
#: 3.5 s against 2.8-2.9 s (2 CPU cores, runs alternated, the channels still vmapped).
WHOLE_FFT_MAX_NPIX = 256


def _swap(x: Array) -> Array:
    return jnp.swapaxes(x, -1, -2)


def _window_ifft2(bins: Complex[Array, "n n"], m: int) -> Complex[Array, "m m"]:
    """``ifft2(bins, norm="ortho")[:m, :m]``; above :data:`WHOLE_FFT_MAX_NPIX` pruned: all
    ``n`` rows along x, then the ``m`` kept columns along y (each 1-D FFT along the
    contiguous axis, transposing in between)."""
    n = bins.shape[-1]
    if m == n or n <= WHOLE_FFT_MAX_NPIX:
        return jnp.fft.ifft2(bins, norm="ortho")[..., :m, :m]
    rows = jnp.fft.ifft(bins, axis=-1, norm="ortho")[..., :m]
    return _swap(jnp.fft.ifft(_swap(rows), axis=-1, norm="ortho")[..., :m])


def _padded_fft2(field: Complex[Array, "m m"], n: int) -> Complex[Array, "n n"]:
    """``fft2(field zero-padded at the end to n x n, norm="ortho")``, pruned: the ``m`` rows
    along x, then all ``n`` columns along y."""
    m = field.shape[-1]
    if m == n:
        return jnp.fft.fft2(field, norm="ortho")
    pad = ((0, 0), (0, n - m))
    rows = jnp.fft.fft(jnp.pad(field, pad), axis=-1, norm="ortho")
    return _swap(jnp.fft.fft(jnp.pad(_swap(rows), pad), axis=-1, norm="ortho"))


def _centring_ramp_2d(n: int, m: int, dtype) -> Complex[Array, "n n"]:
    """The centring ramp of an ``m x m`` crop along both axes of the ``n x n`` bins."""
    ramp = _centring_ramp(n, m // 2, jnp.result_type(dtype, jnp.complex64))
    return ramp[:, None] * ramp[None, :]


def _retina_field_times_ramp(
    bins: Complex[Array, "n n"],
    stack: ChannelStack,
    layer_index: Int[Array, "n n"] | None = None,
) -> Complex[Array, "n n"]:
    """The retinal field times ``exp(-2 pi i (ky + kx) (m // 2) / n)``: its intensity is exact.

    `bins` are the sources' bins times :func:`_centring_ramp_2d` (applied once by
    the caller, not per draw), so the base layer's centred ``m x m`` crop is the
    window ``[0, m)^2`` of their inverse FFT (two slices, no splicing of the FFT layout's
    halves), and the retina is the FFT of the pupil field zero-padded at the end. Pruned,
    with every 1-D FFT along the last axis (see :data:`WHOLE_FFT_MAX_NPIX`): at 512^2 with a
    240 crop (RGB, 8 depth layers, 64 iterations, 2 CPU cores) 2.8-2.9 s, against 3.5 s
    with whole 2-D FFTs and 3.7-4.1 s for the earlier FFT-layout crop, transformed along
    the second to last axis first.
    """
    n, m = bins.shape[-1], stack.crop
    if stack.n_layers == 1:
        u = _window_ifft2(bins, m) * stack.front[0]
    else:
        if layer_index is None:
            raise ConfigError("a stack with several depth layers needs each source's layer_index")

        def add(acc, layer):
            sel = jnp.where(layer_index == layer, bins, 0.0)
            return acc + _window_ifft2(sel, m) * stack.front[layer], None

        u0 = jnp.zeros((m, m), jnp.result_type(bins.dtype, stack.front.dtype))
        # A scan, not a Python loop: unrolled, the 8 layers at 256^2 ran 2x slower.
        u, _ = jax.lax.scan(add, u0, jnp.arange(stack.n_layers))
    # Transfer functions act on the spectrum: the window's circular shift does not matter.
    for kernel, trans in zip(stack.kernels, stack.transmissions, strict=True):
        u = jnp.fft.ifft2(jnp.fft.fft2(u) * kernel) * trans
    return _padded_fft2(u, n)


def stack_field(
    bins: Complex[Array, "n n"],
    stack: ChannelStack,
    layer_index: Int[Array, "n n"] | None = None,
) -> Complex[Array, "n n"]:
    """The retinal field of sources ``bins`` (FFT layout) through one channel's stack.

    `layer_index` gives each bin's depth layer (ignored with one layer).
    """
    ramp = _centring_ramp_2d(bins.shape[-1], stack.crop, bins.dtype)
    return _retina_field_times_ramp(bins * ramp, stack, layer_index) * jnp.conj(ramp)


def _intensity(field: Array, gain: Array) -> Array:
    return gain * (jnp.real(field) ** 2 + jnp.imag(field) ** 2)


# ------------------------------------------------------------------------------ iterations


def iteration_bytes(npix: int, n_channels: int, n_layers: int, itemsize: int = 8) -> int:
    """Working memory (bytes) of one iteration of all channels: the estimate chunks are sized by.

    Per channel: the sources' amplitudes, the field and its spectrum (two complex arrays
    in flight per FFT, XLA's buffers for the FFT's in and out), the layer selection and
    the intensity; about eight complex ``n x n`` arrays, plus one per depth layer beyond
    the first (the scan's carry and one selected layer).
    """
    per_channel = (8 + min(n_layers - 1, 2)) * itemsize * npix * npix
    return n_channels * per_channel + 2 * npix * npix * itemsize  # + the shared phasors


def stack_bytes(npix: int, n_channels: int, n_layers: int, n_planes: int, itemsize: int = 8) -> int:
    """Memory (bytes) of the channels' stacks: a front per depth layer, a kernel and a
    transmission per further plane (`n_planes` planes in front of the pupil at most)."""
    return n_channels * (n_layers + 2 * n_planes) * itemsize * npix * npix


def iterate_intensity(
    amplitudes: Float[Array, "c n n"],
    stacks: ChannelStack,
    key: Key[Array, ""],
    iterations: int,
    *,
    layer_index: Int[Array, "n n"] | None = None,
    phases: str = "uniform",
    chunk: int = 8,
    progress: bool = False,
) -> Float[Array, "c n n"]:
    """The average retinal intensity of `iterations` random-phase draws (FFT layout).

    **Arguments:**

    - `amplitudes`: ``(C, n, n)`` source amplitudes at their bins, per channel.
    - `stacks`: the channels' :class:`ChannelStack` (leading axis ``C``).
    - `key`: randomness of the phases; iteration ``i`` uses ``fold_in(key, i)`` so the draws
      do not depend on `chunk`.
    - `iterations`: number of draws (static int >= 1).
    - `layer_index`: each bin's depth layer (with several layers).
    - `phases`: ``"uniform"`` or ``"quaternary"`` (see
      :func:`~invglare.optics.holographic.sources.random_phasors`); the channels share
      each draw's phases.
    - `chunk`: draws propagated at once (`vmap`); memory is `chunk` times
      :func:`iteration_bytes`. When a chunk holds one draw (``chunk = 1``, or one
      iteration) the channels run one after another too.
    - `progress`: show a progress bar over the chunks (runs a Python loop of jitted
      chunks: not for use inside `jit` / `grad`).

    **Returns:** the mean intensity ``(C, n, n)``.
    """
    if not isinstance(iterations, int | np.integer) or isinstance(iterations, bool):
        raise ConfigError(f"iterations must be an integer >= 1, got {iterations!r}")
    if iterations < 1:
        raise ConfigError(f"iterations must be >= 1, got {iterations}")
    if not isinstance(chunk, int) or chunk < 1:
        raise ConfigError(f"chunk must be an integer >= 1, got {chunk!r}")
    n_chunks = -(-iterations // chunk)
    size = -(-iterations // n_chunks)  # the smallest chunk that still needs n_chunks
    n = amplitudes.shape[-1]
    dtype = jnp.result_type(amplitudes.dtype, jnp.complex64)
    # The centring ramp goes into the amplitudes once, not into every draw's bins.
    ramped = amplitudes * _centring_ramp_2d(n, stacks.crop, dtype)

    def one(i):
        phasor = random_phasors(jax.random.fold_in(key, i), (n, n), phases, dtype)

        def channel(amp, stack):
            field = _retina_field_times_ramp(amp * phasor, stack, layer_index)
            return _intensity(field, stack.gain)

        if size == 1:
            # One draw at a time, one channel at a time: the smallest working set, fastest
            # on a CPU (RGB, 8 depth layers, 2 cores: 0.12 s against 0.13 s at 256^2 x 16,
            # 2.3 s against 2.7 s at 512^2 x 64, than the channels side by side by vmap).
            out = jax.lax.map(lambda a: channel(*a), (ramped, stacks))
        else:
            out = jax.vmap(channel)(ramped, stacks)
        return jnp.where(i < iterations, out, 0.0)

    def block(start):
        return jnp.sum(jax.vmap(one)(start + jnp.arange(size)), axis=0)

    starts = jnp.arange(n_chunks) * size
    if progress:
        from tqdm import tqdm

        run = jax.jit(block)
        total = None
        for s in tqdm(np.asarray(starts), desc="iterations", unit=f"x{size}", disable=None):
            part = run(jnp.asarray(s))
            total = part if total is None else total + part
        return total / iterations

    def body(acc, start):
        return acc + block(start), None

    acc0 = jnp.zeros(amplitudes.shape, jnp.finfo(dtype).dtype)
    total, _ = jax.lax.scan(body, acc0, starts)
    return total / iterations


# ------------------------------------------------------------------------------ limit


def point_response(
    stack: ChannelStack, bin_yx: tuple[int, int] | Int[Array, " 2"], layer: int = 0
) -> Float[Array, "n n"]:
    """``gain |h_j|^2`` of a unit source at FFT bin `bin_yx` in depth `layer`, moved to bin 0.

    The PSF a source at that bin spreads its light with (FFT layout, energy per pixel;
    one channel).
    """
    n = stack.npix
    ky, kx = bin_yx
    ramp = _centring_ramp_2d(n, stack.crop, stack.front.dtype)
    delta = jnp.zeros((n, n), ramp.dtype).at[ky, kx].set(ramp[ky, kx])
    one_layer = eqx.tree_at(lambda s: s.front, stack, stack.front[layer][None])
    psf = _intensity(_retina_field_times_ramp(delta, one_layer), stack.gain)
    return jnp.roll(psf, (-ky, -kx), axis=(0, 1))


def tile_weights(npix: int, tiles: int, lo: int = 0, hi: int | None = None) -> np.ndarray:
    """Bilinear (tent) weights of `tiles` tile centres along one axis: ``(tiles, npix)``.

    Centres are evenly spread over ``[lo, hi)`` (default the whole axis); the weights sum to
    1 at every pixel, and beyond the outer centres the outer tile takes everything.
    """
    hi = npix if hi is None else hi
    if not isinstance(tiles, int) or tiles < 1:
        raise ConfigError(f"psf tiles must be an integer >= 1, got {tiles!r}")
    width = (hi - lo) / tiles
    centres = lo + (np.arange(tiles) + 0.5) * width
    i = np.arange(npix, dtype=float)
    w = np.clip(1.0 - np.abs(i[None, :] - centres[:, None]) / width, 0.0, 1.0)
    w[0, i <= centres[0]] = 1.0
    w[-1, i >= centres[-1]] = 1.0
    return w / w.sum(axis=0, keepdims=True)


def speckle_free(
    intensity_bins: Float[Array, "c n n"],
    stacks: ChannelStack,
    *,
    layer_index: Int[Array, "n n"] | None = None,
    tiles: int = 1,
    region: tuple[int, int, int, int] | None = None,
    to_bins: Callable[[np.ndarray], np.ndarray] | None = None,
) -> Float[Array, "c n n"]:
    """The speckle-free image: the expectation of :func:`iterate_intensity` over the phases.

    **Arguments:**

    - `intensity_bins`: ``|C|^2`` per channel at the bins (FFT layout).
    - `stacks`: the channels' stacks.
    - `layer_index`: each bin's depth layer (with several layers).
    - `tiles`: PSFs per axis (1: one PSF, exact for a stack whose layers all sit in the
      pupil plane; see the module docstring).
    - `region`: ``(row0, row1, col0, col1)`` of the output image the tiles cover (default
      the whole grid), in image layout.
    - `to_bins`: the map from image layout to FFT layout
      (:func:`~invglare.optics.holographic.sources.image_to_bins`), needed with tiles > 1.

    **Returns:** ``(C, n, n)`` intensities, FFT layout.
    """
    c, n, _ = intensity_bins.shape
    n_layers = stacks.front.shape[-3]
    if n_layers > 1 and layer_index is None:
        raise ConfigError("several depth layers need each source's layer_index")
    r0, r1, c0, c1 = (0, n, 0, n) if region is None else region
    if tiles > 1 and to_bins is None:
        raise ConfigError("speckle_free with tiles > 1 needs to_bins (image -> FFT layout)")
    wy = tile_weights(n, tiles, r0, r1)
    wx = tile_weights(n, tiles, c0, c1)
    centres_y = [round(r0 + (t + 0.5) * (r1 - r0) / tiles) for t in range(tiles)]
    centres_x = [round(c0 + (t + 0.5) * (c1 - c0) / tiles) for t in range(tiles)]
    dtype = intensity_bins.dtype
    spectrum = jnp.zeros((c, n, n // 2 + 1), jnp.result_type(dtype, jnp.complex64))
    for ty in range(tiles):
        for tx in range(tiles):
            if tiles == 1:
                weight = None
                bin_yx = (0, 0)
            else:
                img = np.zeros((n, n))
                img[centres_y[ty], centres_x[tx]] = 1.0
                ky, kx = (int(v[0]) for v in np.nonzero(to_bins(img)))
                bin_yx = (ky, kx)
                weight = jnp.asarray(to_bins(np.outer(wy[ty], wx[tx])), dtype)
            # One scan over the depth layers (not an unrolled loop: the program stays small).
            def add(acc, layer, bin_yx=bin_yx, weight=weight):
                psf = jax.vmap(lambda st: point_response(st, bin_yx, layer))(stacks)
                part = intensity_bins
                if n_layers > 1:
                    part = jnp.where(layer_index == layer, part, 0.0)
                if weight is not None:
                    part = part * weight
                return acc + jnp.fft.rfft2(part) * jnp.fft.rfft2(psf.astype(dtype)), None

            spectrum, _ = jax.lax.scan(add, spectrum, jnp.arange(n_layers))
    return jnp.fft.irfft2(spectrum, s=(n, n))


def speckle_contrast(image: Float[Array, "*shape"], mask=None) -> Float[Array, ""]:
    """``std / mean`` of an image's values (where `mask`): 1 for fully developed speckle."""
    x = jnp.asarray(image)
    if mask is None:
        return jnp.std(x) / jnp.mean(x)
    m = jnp.asarray(mask, x.dtype)
    mean = jnp.sum(x * m) / jnp.sum(m)
    var = jnp.sum((x - mean) ** 2 * m) / jnp.sum(m)
    return jnp.sqrt(var) / mean
