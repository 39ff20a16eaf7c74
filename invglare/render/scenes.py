"""Small procedural HDR scenes, so that glare can be rendered with nothing downloaded.

Each scene is a pure function of `(npix, seed)` returning a linear RGB image
`(npix, npix, 3)` float32 in **cd/m^2** (Rec. 709 primaries, luminance = Rec. 709
weighted sum) and its pixel scale in degrees per pixel. The seed only jitters
details (lamp brightness, texture, window layout); the layout is the same for
every seed, so scenes at the same `npix` are comparable.

| name                         | deg/px | content                                             |
|------------------------------|--------|-----------------------------------------------------|
| `street_lights_at_night`     | 0.05   | road 0.1-2, sky ~0.03, lamp heads ~1e4 (sodium, LED) |
| `sunlit_specular_highlight`  | 0.02   | daylight ~1e3, sky ~6e3, a glint of 4e6 on a car    |
| `candle`                     | 0.03   | dim room ~1, wax ~30, flame ~5e3 (about 1900 K)      |

The pixel scale is fixed per scene (0.02-0.05 deg/px, the range of the glare
PSFs invglare computes), so the field of view is `npix * pixel_scale_deg`; the
layout is given in fractions of the frame and the light sources in degrees, so
sources keep their angular size when `npix` changes.

Each scene also has a depth buffer (:data:`SCENE_DEPTHS`, planar depth in metres, the
holographic eye's default encoding), written beside it by ``invglare scene --depth``: the
eye's height over the ground, the sources' sizes and the rooms give the distances.

Colours of light sources are the linear sRGB chromaticities of Planckian
radiators (computed once with colour-science, CIE 1931 2° observer, scaled to unit
luminance and hard-coded here so that generating a scene does not import it).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from invglare.errors import ConfigError, InputDataError
from invglare.files.exr import first_flagged, nonfinite_pixels

__all__ = [
    "SCENES",
    "SCENE_DEPTHS",
    "candle",
    "candle_depth_m",
    "street_lights_at_night",
    "street_lights_at_night_depth_m",
    "sunlit_specular_highlight",
    "sunlit_specular_highlight_depth_m",
    "validate_scene",
    "write_scene",
]

# Linear sRGB of blackbodies, luminance 1 (negative components of the 1900 K one clipped).
_SODIUM_2000K = (2.52, 0.647, 0.0205)  # high-pressure sodium is close to a 2000 K source
_LED_4000K = (1.414, 0.924, 0.533)
_FLAME_1900K = (2.64, 0.614, 0.01)
_NIGHT_SKY = (0.55, 0.9, 1.9)
_DAY_SKY = (0.75, 0.98, 1.45)
_WHITE = (1.0, 1.0, 1.0)

#: Depth of the sky (m): far enough that every wavefront from it is plane at the eye.
SKY_DEPTH_M = 1000.0
#: Height of the eye over the ground (m), which sets the depth of every ground pixel.
EYE_HEIGHT_M = 1.6


def _colour(rgb) -> Array:
    c = jnp.asarray(rgb, jnp.float32)
    return c / (c @ jnp.asarray([0.2126, 0.7152, 0.0722], jnp.float32))


def _grid(npix: int) -> tuple[Array, Array]:
    """Row and column coordinates (pixels), as (npix, 1) and (1, npix)."""
    c = jnp.arange(npix, dtype=jnp.float32)
    return c[:, None], c[None, :]


def _disk(y, x, cy, cx, r) -> Array:
    """Anti-aliased disk coverage (one-pixel linear ramp across the edge)."""
    return jnp.clip(r + 0.5 - jnp.hypot(y - cy, x - cx), 0.0, 1.0)


def _box(y, x, top, left, bottom, right) -> Array:
    """Anti-aliased coverage of the rectangle [top, bottom) x [left, right) in pixel edges."""
    fy = jnp.clip(jnp.minimum(y + 0.5, bottom) - jnp.maximum(y - 0.5, top), 0.0, 1.0)
    fx = jnp.clip(jnp.minimum(x + 0.5, right) - jnp.maximum(x - 0.5, left), 0.0, 1.0)
    return fy * fx


def _smooth_noise(key, npix: int, cells: int) -> Array:
    """Smooth noise in [0, 1]: uniform values on a coarse grid, bilinearly upsampled."""
    coarse = jax.random.uniform(key, (cells, cells), jnp.float32)
    return jax.image.resize(coarse, (npix, npix), "linear")


def _key(seed: int | ArrayLike) -> Array:
    if isinstance(seed, int | np.integer):
        return jax.random.PRNGKey(int(seed))
    return jnp.asarray(seed)


def _check_npix(npix: int, minimum: int = 16) -> int:
    if not isinstance(npix, int | np.integer) or npix < minimum:
        raise ConfigError(f"scene npix must be an int >= {minimum}; got {npix!r}")
    return int(npix)


def _street_lamps(npix: int, scale: float) -> tuple[Array, Array, Array, Array]:
    """The six lamps, receding along a line towards a vanishing point right of centre:
    their distance along the row `t` (0-1), centres (rows, columns) and radii (px)."""
    t = jnp.linspace(0.0, 1.0, 6) ** 0.7
    cy = (0.12 + (0.40 - 0.12) * t) * npix
    cx = (0.08 + (0.62 - 0.08) * t) * npix
    radius_px = jnp.maximum((0.5 - 0.38 * t) / scale, 0.75)
    return t, cy, cx, radius_px


def _ground_depth_m(y: Array, horizon: float, scale: float) -> Array:
    """Planar depth (m) of flat ground `EYE_HEIGHT_M` below the eye, rows below `horizon`."""
    below_rad = jnp.radians(jnp.maximum(y - horizon + 0.5, 0.5) * scale)
    return jnp.minimum(EYE_HEIGHT_M / jnp.tan(below_rad), SKY_DEPTH_M)


def street_lights_at_night(
    npix: int = 256, seed: int | ArrayLike = 0
) -> tuple[Float[Array, "npix npix 3"], float]:
    """A road at night under a receding row of street lamps.

    Sky about 0.03 cd/m^2, road 0.1-0.5 with pools of light up to ~2 under the
    lamps, a building with a few lit windows (~10-30), and six lamp heads of
    5e3-2e4 cd/m^2, alternately high-pressure sodium (orange) and 4000 K LED,
    shrinking from 0.5° to 0.12° with distance. 0.05 deg/px.

    **Arguments:**

    - `npix`: image size in pixels (>= 16).
    - `seed`: int or `jax.random` key; jitters lamp brightness, texture and windows.

    **Returns:** `(image, pixel_scale_deg)`, image `(npix, npix, 3)` float32 cd/m^2.

    **Example:**

    ```python
    img, scale = street_lights_at_night(256, seed=0)   # scale == 0.05
    ```
    """
    npix = _check_npix(npix)
    scale = 0.05
    k_lamp, k_tex, k_win, k_wlum = jax.random.split(_key(seed), 4)
    y, x = _grid(npix)
    horizon = 0.45 * npix
    sky_t = jnp.clip(y / horizon, 0, 1)
    sky = (0.015 + 0.03 * sky_t)[..., None] * _colour(_NIGHT_SKY)
    depth = jnp.clip((y - horizon) / (npix - horizon), 0, 1)  # 0 at the horizon, 1 at the bottom
    texture = 0.8 + 0.4 * _smooth_noise(k_tex, npix, 24)
    road = ((0.1 + 0.25 * depth) * texture)[..., None] * _colour(_WHITE)
    image = jnp.where((y < horizon)[..., None], sky, road)

    # A building on the right with a grid of windows, a third of them lit.
    building = _box(y, x, 0.2 * npix, 0.7 * npix, horizon, 0.95 * npix)
    image = image * (1 - building[..., None]) + building[..., None] * 0.02 * _colour(_WHITE)
    lit = jax.random.bernoulli(k_win, 0.35, (5, 4))
    lum = jax.random.uniform(k_wlum, (5, 4), minval=10.0, maxval=30.0)
    for i in range(5):
        for j in range(4):
            top, left = (0.23 + 0.04 * i) * npix, (0.73 + 0.055 * j) * npix
            win = _box(y, x, top, left, top + 0.02 * npix, left + 0.03 * npix)
            level = jnp.where(lit[i, j], lum[i, j], 0.0)
            image = image + (win * level)[..., None] * _colour(_SODIUM_2000K) * 0.3

    t, cy, cx, radius_px = _street_lamps(npix, scale)
    n = t.shape[0]
    brightness = 1e4 * jnp.exp(jax.random.uniform(k_lamp, (n,), minval=-0.7, maxval=0.7))
    for i in range(n):
        colour = _colour(_SODIUM_2000K if i % 2 == 0 else _LED_4000K)
        head = _disk(y, x, cy[i], cx[i], radius_px[i])
        # Pool of light on the road below the lamp, weaker with distance.
        pool_y = horizon + (npix - horizon) * (1 - t[i]) * 0.9
        pool = (
            2.0
            * (1 - 0.8 * t[i])
            * jnp.exp(-(((y - pool_y) / (0.06 * npix)) ** 2) - ((x - cx[i]) / (0.1 * npix)) ** 2)
        )
        pool = jnp.where(y > horizon, pool, 0.0)
        image = image * (1 - head[..., None]) + (head * brightness[i] + pool)[..., None] * colour
    return jnp.maximum(image, 0).astype(jnp.float32), scale


def sunlit_specular_highlight(
    npix: int = 256, seed: int | ArrayLike = 0
) -> tuple[Float[Array, "npix npix 3"], float]:
    """A sunlit street with a car whose paint reflects the sun in a tiny glint.

    Sky 4e3-8e3 cd/m^2, a facade ~800 with darker windows (~200), asphalt ~400,
    dark car paint ~150, a sun glint of 4e6 cd/m^2 on one pixel (a Gaussian of
    0.6 px) and a weaker glint of ~2e5 on a window. 0.02 deg/px.

    **Arguments / returns:** as `street_lights_at_night`.

    ```python
    img, scale = sunlit_specular_highlight(128)
    ```
    """
    npix = _check_npix(npix)
    scale = 0.02
    k_tex, k_glint = jax.random.split(_key(seed), 2)
    y, x = _grid(npix)
    texture = 0.85 + 0.3 * _smooth_noise(k_tex, npix, 32)
    sky = (8e3 - 4e3 * y / (0.3 * npix))[..., None] * _colour(_DAY_SKY)
    facade = (800.0 * texture)[..., None] * _colour((1.1, 1.0, 0.85))
    ground = (400.0 * texture)[..., None] * _colour(_WHITE)
    image = jnp.where((y < 0.3 * npix)[..., None], sky, facade)
    image = jnp.where((y >= 0.75 * npix)[..., None], ground, image)
    for i in range(3):
        for j in range(5):
            top, left = (0.35 + 0.12 * i) * npix, (0.06 + 0.19 * j) * npix
            win = _box(y, x, top, left, top + 0.07 * npix, left + 0.1 * npix)
            image = image * (1 - 0.75 * win[..., None])
    car = _box(y, x, 0.66 * npix, 0.2 * npix, 0.86 * npix, 0.75 * npix)
    image = image * (1 - car[..., None]) + (150.0 * car)[..., None] * _colour((0.5, 0.8, 1.6))

    # The sun glint sits on a pixel centre, so that pixel holds the peak luminance.
    jitter = jax.random.randint(k_glint, (2,), -2, 3).astype(jnp.float32)
    gy, gx = jnp.round(0.7 * npix) + jitter[0], jnp.round(0.42 * npix) + jitter[1]
    glint = 4e6 * jnp.exp(-((y - gy) ** 2 + (x - gx) ** 2) / (2 * 0.6**2))
    second = 2e5 * jnp.exp(-((y - 0.38 * npix) ** 2 + (x - 0.5 * npix) ** 2) / (2 * 0.8**2))
    image = image + (glint + second)[..., None] * _colour(_WHITE)
    return jnp.maximum(image, 0).astype(jnp.float32), scale


def candle(npix: int = 256, seed: int | ArrayLike = 0) -> tuple[Float[Array, "npix npix 3"], float]:
    """A candle in a dim room.

    Walls ~0.3-2 cd/m^2 lit warmly by the flame, a table, a wax candle glowing at
    ~30, and a teardrop flame of 0.3° x 0.9° peaking near 5e3 cd/m^2 with the
    colour of a 1900 K radiator, a faint blue base and a dark wick. 0.03 deg/px.

    **Arguments / returns:** as `street_lights_at_night`.

    ```python
    img, scale = candle(128, seed=1)
    ```
    """
    npix = _check_npix(npix)
    scale = 0.03
    k_tex, k_flicker = jax.random.split(_key(seed), 2)
    y, x = _grid(npix)
    warm = _colour(_FLAME_1900K)
    fy, fx = 0.42 * npix, 0.5 * npix  # centre of the flame
    d = jnp.hypot(y - fy, x - fx) / npix
    texture = 0.9 + 0.2 * _smooth_noise(k_tex, npix, 16)
    wall = ((0.3 + 1.7 / (1 + (d / 0.25) ** 2)) * texture)[..., None] * (0.4 * warm + 0.6)
    table = ((0.2 + 1.0 / (1 + (d / 0.3) ** 2)) * texture)[..., None] * (0.6 * warm + 0.4)
    image = jnp.where((y >= 0.7 * npix)[..., None], table, wall)

    half_w = max(0.25 / scale, 2.0)  # candle body: 0.5° wide
    body = _box(y, x, fy + 0.5 / scale, fx - half_w, 0.72 * npix, fx + half_w)
    image = image * (1 - body[..., None]) + (30.0 * body)[..., None] * _colour((1.2, 1.0, 0.8))

    # Flame: an ellipse 0.3° wide and 0.9° tall, narrowing to a tip at the top.
    flicker = jnp.exp(jax.random.uniform(k_flicker, (), minval=-0.1, maxval=0.1))
    a, b = 0.15 / scale, 0.45 / scale  # semi-axes (px)
    v = (y - fy) / b  # -1 at the tip, +1 at the base
    width = a * jnp.sqrt(jnp.clip((1 + v) / 2, 0, 1)) * jnp.clip(1.4 - 0.4 * v, 0, None)
    inside = jnp.clip(width + 0.5 - jnp.abs(x - fx), 0, 1) * jnp.clip((1 - jnp.abs(v)) * b, 0, 1)
    profile = jnp.exp(-2 * ((x - fx) / (a + 0.5)) ** 2 - 1.5 * v**2)
    flame = 5e3 * flicker * inside * profile
    base = inside * jnp.clip((v - 0.6) / 0.4, 0, 1)  # the blue zone at the bottom
    wick = _box(y, x, fy + 0.6 * b, fx - 0.5, fy + b + 3, fx + 0.5)
    colour = (1 - base)[..., None] * warm + base[..., None] * _colour((0.3, 0.5, 2.5))
    image = image * (1 - inside[..., None]) + (flame * (1 - 0.9 * base))[..., None] * colour
    image = image * (1 - 0.9 * wick[..., None])
    return jnp.maximum(image, 0).astype(jnp.float32), scale


def street_lights_at_night_depth_m(npix: int = 256) -> Float[Array, "npix npix"]:
    """Planar depth (m) of :func:`street_lights_at_night`: the road from the eye's height
    (1.6 m, so 13 m at the bottom of a 256-pixel frame), the building's facade at 60 m,
    the lamp heads (0.4 m across) where their angular size puts them (23-95 m), the sky at
    1000 m. The same for every seed."""
    npix = _check_npix(npix)
    scale = 0.05
    y, x = _grid(npix)
    horizon = 0.45 * npix
    depth = jnp.where(y < horizon, SKY_DEPTH_M, _ground_depth_m(y, horizon, scale))
    building = _box(y, x, 0.2 * npix, 0.7 * npix, horizon, 0.95 * npix)
    depth = jnp.where(building > 0.5, 60.0, depth)
    _, cy, cx, radius_px = _street_lamps(npix, scale)
    for i in range(cy.shape[0]):
        distance = 0.2 / jnp.tan(jnp.radians(radius_px[i] * scale))
        depth = jnp.where(_disk(y, x, cy[i], cx[i], radius_px[i]) > 0.5, distance, depth)
    return jnp.broadcast_to(depth, (npix, npix)).astype(jnp.float32)


def sunlit_specular_highlight_depth_m(npix: int = 256) -> Float[Array, "npix npix"]:
    """Planar depth (m) of :func:`sunlit_specular_highlight`: the facade 30 m away, the
    ground from its foot to 5 m at the bottom row, the car at 12 m (the glints on it and on
    a window with them), the sky at 1000 m."""
    npix = _check_npix(npix)
    y, x = _grid(npix)
    near = jnp.clip((y - 0.75 * npix) / (0.25 * npix), 0.0, 1.0)  # 0 at the facade's foot
    ground = 1.0 / (1.0 / 30.0 + near * (1.0 / 5.0 - 1.0 / 30.0))
    depth = jnp.where(y < 0.3 * npix, SKY_DEPTH_M, jnp.where(y >= 0.75 * npix, ground, 30.0))
    car = _box(y, x, 0.66 * npix, 0.2 * npix, 0.86 * npix, 0.75 * npix)
    depth = jnp.where(car > 0.5, 12.0, depth)
    return jnp.broadcast_to(depth, (npix, npix)).astype(jnp.float32)


def candle_depth_m(npix: int = 256) -> Float[Array, "npix npix"]:
    """Planar depth (m) of :func:`candle`: the wall 3 m away, the table from 1.5 m at its
    back edge to 0.6 m at the bottom row, the candle and its flame at 1 m."""
    npix = _check_npix(npix)
    scale = 0.03
    y, x = _grid(npix)
    near = jnp.clip((y - 0.7 * npix) / (0.3 * npix), 0.0, 1.0)
    table = 1.0 / (1.0 / 1.5 + near * (1.0 / 0.6 - 1.0 / 1.5))
    depth = jnp.where(y >= 0.7 * npix, table, 3.0)
    fy, fx = 0.42 * npix, 0.5 * npix
    half_w = max(0.25 / scale, 2.0)
    candle_and_flame = _box(y, x, fy - 0.45 / scale, fx - half_w, 0.72 * npix, fx + half_w)
    depth = jnp.where(candle_and_flame > 0.5, 1.0, depth)
    return jnp.broadcast_to(depth, (npix, npix)).astype(jnp.float32)


#: The bundled scenes by name: `fn(npix, seed) -> (image, pixel_scale_deg)`.
SCENES: dict[str, Callable[..., tuple[Array, float]]] = {
    "street_lights_at_night": street_lights_at_night,
    "sunlit_specular_highlight": sunlit_specular_highlight,
    "candle": candle,
}

#: Their depth buffers by name: `fn(npix) -> (npix, npix)` planar depth in metres.
SCENE_DEPTHS: dict[str, Callable[[int], Array]] = {
    "street_lights_at_night": street_lights_at_night_depth_m,
    "sunlit_specular_highlight": sunlit_specular_highlight_depth_m,
    "candle": candle_depth_m,
}


def write_scene(
    name: str,
    path: str | os.PathLike[str],
    npix: int = 256,
    seed: int = 0,
    depth_path: str | os.PathLike[str] | None = None,
) -> Path:
    """Generate a bundled scene and write it as an RGB EXR with its `pixelScaleDeg`.

    The header also records `invglareScene` (the name), `invglareSeed` and
    `units` (`"cd/m^2"`). Written atomically. With `depth_path`, the scene's depth
    buffer (:data:`SCENE_DEPTHS`) goes there too, as a ``Z`` channel in metres
    (`units` ``"m"``), the file ``invglare render --depth`` reads for a holographic eye.

    **Raises:** `ConfigError` for an unknown name (listing the valid ones).

    ```python
    write_scene("candle", "candle.exr", npix=256, depth_path="candle_depth.exr")
    ```
    """
    fn = SCENES.get(name) if isinstance(name, str) else None
    if fn is None:
        raise ConfigError(f"unknown scene {name!r}; valid names: {', '.join(SCENES)}")
    from invglare.files.exr import write_exr  # imported here: scenes are usable without OpenEXR

    image, scale = fn(npix, seed)
    if depth_path is not None:
        write_exr(
            depth_path,
            np.asarray(SCENE_DEPTHS[name](npix))[..., None],
            pixel_scale_deg=scale,
            channels=("Z",),
            attrs={"invglareScene": name, "units": "m"},
        )
    return write_exr(
        path,
        np.asarray(image),
        pixel_scale_deg=scale,
        attrs={"invglareScene": name, "invglareSeed": int(seed), "units": "cd/m^2"},
    )


def validate_scene(image: ArrayLike, *, name: str = "scene") -> np.ndarray:
    """Check that an HDR scene is a finite, non-negative `(H, W)` or `(H, W, C)` image.

    Call it on concrete data at the edge (after reading a file, before `jit`).

    **Arguments:**

    - `image`: the pixels (numpy or JAX array).
    - `name`: what to call it in messages (e.g. the file name).

    **Returns:** the pixels as a numpy array.

    **Raises:** `InputDataError` for a wrong number of dimensions or an empty
    image, for NaN/Inf pixels and for negative pixels, naming how many there are
    and where the first one is.

    ```python
    validate_scene(np.full((4, 4, 3), 1.0))   # passes
    ```
    """
    try:
        arr = np.asarray(image)
    except Exception as e:  # a tracer or an object numpy cannot take
        raise InputDataError(f"{name}: cannot read the pixels as an array ({e})") from e
    if arr.ndim not in (2, 3) or 0 in arr.shape:
        raise InputDataError(
            f"{name} must have shape (H, W) or (H, W, C) with no empty axis; got {arr.shape}"
        )
    if arr.dtype.kind not in "fiub":
        raise InputDataError(f"{name} must hold real numbers; got dtype {arr.dtype}")
    channels = ("R", "G", "B") if arr.ndim == 3 and arr.shape[-1] == 3 else ()

    found = nonfinite_pixels(arr, channels)
    if found is not None:
        n_bad, detail = found
        raise InputDataError(
            f"{name} has {n_bad} non-finite pixel value(s) {detail}; "
            "expected finite linear values (cd/m^2)"
        )
    neg = arr < 0
    if neg.any():
        raise InputDataError(
            f"{name} has {int(neg.sum())} negative pixel value(s) (minimum {float(arr.min()):g}), "
            f"first at {first_flagged(neg, channels)}; expected linear values >= 0 (cd/m^2)"
        )
    return arr
