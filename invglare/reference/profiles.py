"""Radial profiles, encircled energy, and conversions between 1-D GSFs and 2-D PSFs.

Two representations of a rotationally symmetric glare function meet here:

- a **GSF** (glare spread function): a 1-D function of the angle from the source
  in degrees, with values in **sr⁻¹** (fraction of the light per steradian) —
  the CIE function, a published table, a measured straylight curve;
- a **PSF** on an output grid (:class:`invglare._core.grids.AngularGrid`):
  a 2-D array holding, per pixel, the **fraction of the light in that pixel**
  — the normalisation of `invglare.optics.fraunhofer` and of every model.

The bridge is the pixel solid angle ``dOmega = (pixel scale in rad)²`` (small
angles): ``PSF ≈ GSF × dOmega`` pixel by pixel (:func:`gsf_to_psf` integrates
the GSF over each pixel), and ``GSF ≈ radial mean of PSF / dOmega``
(:func:`psf_to_gsf`).

Pixel geometry follows the sampling module: the source sits at the centre of
pixel ``(npix // 2, npix // 2)`` (row, column) unless a `centre` is given, in
fractional pixel coordinates ``(row, col)``.

Everything that touches a PSF is `jax.numpy` and works under `jit` when the
bin count is static; file loading and table validation are numpy, at the edge.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from invglare._core.checks import as_float, is_concrete
from invglare._core.grids import AngularGrid
from invglare._core.maths import safe_sqrt
from invglare.aperture.shapes.coverage import curved_edge_coverage
from invglare.errors import ConfigError, InputDataError, PhysicsRangeError

__all__ = [
    "NORMALISATIONS",
    "TABLE_SUFFIXES",
    "RadialTable",
    "ReferenceImage",
    "encircled_energy",
    "gsf_to_psf",
    "load_reference_psf",
    "psf_to_gsf",
    "radial_profile",
]

NORMALISATIONS = ("none", "unit")
TABLE_SUFFIXES = (".csv", ".txt", ".tsv", ".dat")


def _check_scale(pixel_scale_deg) -> None:
    if not is_concrete(pixel_scale_deg):
        return
    value = np.asarray(pixel_scale_deg, dtype=float)
    if value.shape != () or not (np.isfinite(value) and value > 0):
        raise PhysicsRangeError(
            f"pixel_scale_deg must be one finite number of degrees per pixel > 0, got {value}"
        )


def _image_and_scale(
    psf: Float[ArrayLike, "*batch h w"], pixel_scale_deg: Float[ArrayLike, ""]
) -> tuple[Float[Array, "*batch h w"], Float[Array, ""]]:
    """The image (at least 2-D) and its pixel scale (deg), checked, as float arrays."""
    image = as_float(psf)
    if image.ndim < 2:
        raise ValueError(f"psf must have at least 2 dimensions (h, w), got shape {image.shape}")
    _check_scale(pixel_scale_deg)
    return image, as_float(pixel_scale_deg)


def _centre_and_radius(
    shape: tuple[int, ...], centre
) -> tuple[Array, Array, Float[Array, "h w"], float]:
    """Pixel-centre distances (px) from `centre`, and the default outer radius (px).

    The default radius is the distance from the grid's own centre pixel to the
    nearest array edge: the largest circle whose annuli are complete.
    """
    h, w = shape[-2], shape[-1]
    if centre is None:
        cy, cx = jnp.asarray(float(h // 2)), jnp.asarray(float(w // 2))
    else:
        c = as_float(centre)
        if c.shape != (2,):
            raise ValueError(f"centre must be (row, col) in pixels, got shape {c.shape}")
        cy, cx = c[0], c[1]
    rows = jnp.arange(h, dtype=cy.dtype)[:, None] - cy
    cols = jnp.arange(w, dtype=cx.dtype)[None, :] - cx
    r2 = rows * rows + cols * cols
    # sqrt has an infinite slope at 0: keep a centre that sits on a pixel differentiable.
    r = safe_sqrt(r2)
    r_edge = float(min(h // 2 + 0.5, h - 0.5 - h // 2, w // 2 + 0.5, w - 0.5 - w // 2))
    return cy, cx, r, r_edge


# ------------------------------------------------------------------------------ profiles


def radial_profile(
    psf: Float[ArrayLike, "*batch h w"],
    pixel_scale_deg: Float[ArrayLike, ""],
    n_bins: int | None = None,
    max_angle_deg: Float[ArrayLike, ""] | None = None,
    centre: Float[ArrayLike, " 2"] | None = None,
) -> tuple[Float[Array, " n_bins"], Float[Array, "*batch n_bins"]]:
    """Azimuthal mean of an image in equal-width annuli around the source.

    Annulus ``i`` holds the pixels whose centres lie at distances ``[i, i + 1) ×
    max_angle_deg / n_bins`` from `centre`; the profile is the plain mean of
    their values and the returned angle is the mean distance of those pixel
    centres (not the annulus mid-point), so a profile that is linear in the
    angle is recovered exactly and a smooth one to second order in the bin
    width. An annulus with no pixel centre gives NaN for both.

    **Arguments:**

    - `psf`: ``(..., h, w)`` image (any units; leading axes are batched).
    - `pixel_scale_deg`: degrees per pixel.
    - `n_bins`: number of annuli (static). Default: the outer radius in whole
      pixels, i.e. annuli about one pixel wide.
    - `max_angle_deg`: outer radius. Default: the distance from the grid's
      centre pixel ``(h // 2, w // 2)`` to the nearest array edge, so that every
      annulus is complete.
    - `centre`: ``(row, col)`` of the source in fractional pixels; default the
      centre pixel. The bins do not move smoothly with it (no gradient).

    **Returns:** ``(theta_deg, mean)``: shapes ``(n_bins,)`` and ``(..., n_bins)``.
    For a batch the angles are shared (they depend only on the geometry).

    **Raises:** `PhysicsRangeError` for a non-positive pixel scale; `ValueError`
    for an image of fewer than 2 dimensions, or when the default bin count is
    needed but `max_angle_deg` / `pixel_scale_deg` are traced.

    **Example:**

    ```python
    theta, prof = radial_profile(psf, 0.01)             # ~1-pixel annuli
    theta, prof = radial_profile(psf, 0.01, 20, 2.0)    # 20 annuli out to 2 deg
    ```
    """
    image, scale = _image_and_scale(psf, pixel_scale_deg)
    _, _, r_px, r_edge = _centre_and_radius(image.shape, centre)
    r_max_px = r_edge if max_angle_deg is None else as_float(max_angle_deg) / scale
    if n_bins is None:
        if not is_concrete(r_max_px):
            raise ValueError("n_bins must be given when max_angle_deg or the pixel scale is traced")
        n_bins = max(math.floor(float(r_max_px) + 1e-9), 1)
    if int(n_bins) < 1:
        raise ValueError(f"n_bins must be >= 1, got {n_bins}")
    n_bins = int(n_bins)
    width_px = r_max_px / n_bins

    # Pixels outside the outer radius go to an overflow bin that is dropped.
    idx = jnp.floor(r_px / width_px).astype(jnp.int32)
    idx = jnp.where((idx >= 0) & (idx < n_bins), idx, n_bins).reshape(-1)
    flat = image.reshape((*image.shape[:-2], -1))
    counts = jnp.zeros(n_bins + 1, image.dtype).at[idx].add(1.0)[:n_bins]
    r_sum = jnp.zeros(n_bins + 1, r_px.dtype).at[idx].add(r_px.reshape(-1))[:n_bins]
    v_sum = jnp.zeros((*flat.shape[:-1], n_bins + 1), image.dtype).at[..., idx].add(flat)
    v_sum = v_sum[..., :n_bins]
    filled = counts > 0
    safe = jnp.where(filled, counts, 1.0)
    theta = jnp.where(filled, r_sum / safe, jnp.nan) * scale
    mean = jnp.where(filled, v_sum / safe, jnp.nan)
    return theta, mean


def encircled_energy(
    psf: Float[ArrayLike, "*batch h w"],
    pixel_scale_deg: Float[ArrayLike, ""],
    radii_deg: Float[ArrayLike, "*radii"],
    centre: Float[ArrayLike, " 2"] | None = None,
    total: Float[ArrayLike, "*batch"] | None = None,
) -> Float[Array, "*batch *radii"]:
    """Fraction of a PSF within circles of the given radii, with partial pixels.

    Each pixel counts with the fraction of its area inside the circle. That
    fraction comes from `invglare.aperture.curved_edge_coverage`: the circle is
    taken as a straight edge across the pixel (exact half-plane coverage, along
    the radial normal through the pixel centre) corrected to first order for the
    circle's curvature ``1 / R``, and capped at ``pi R²`` (a circle smaller than
    a pixel cannot cover more). Measured on a uniform image, the covered area is
    within 5e-4 of ``pi R²`` for R >= 2 px and 1e-4 for R >= 3 px, whatever the
    sub-pixel centre; below 1 px the weights are rough (errors up to ~0.4 of
    ``pi R²`` off-centre, exact for a centred circle of R <= 0.5 px). The weights
    are continuous in `radii_deg` and `centre`, so the result is differentiable
    in both.

    **Arguments:**

    - `psf`: ``(..., h, w)`` image, e.g. energy per pixel.
    - `pixel_scale_deg`: degrees per pixel.
    - `radii_deg`: radii (deg), any shape.
    - `centre`: ``(row, col)`` of the source in fractional pixels; default the
      centre pixel ``(h // 2, w // 2)``.
    - `total`: what to divide by; default the PSF's sum over the array (then the
      result is the fraction of the array's content). Pass 1 for a unit-energy
      PSF whose tails run off the array.

    **Returns:** shape ``(..., *radii.shape)``.

    **Example:**

    ```python
    encircled_energy(psf, 0.01, jnp.array([0.05, 0.1, 0.5]))
    ```
    """
    image, scale = _image_and_scale(psf, pixel_scale_deg)
    radii = as_float(radii_deg)
    r_out = radii.reshape(-1) / scale

    # Outward normal of the circle at each pixel: the radial direction (any unit
    # vector at the centre pixel, whose coverage is then set by the pi R² cap or 1).
    cy, cx, r_px, _ = _centre_and_radius(image.shape, centre)
    h, w = image.shape[-2:]
    dy = jnp.arange(h, dtype=r_px.dtype)[:, None] - cy
    dx = jnp.arange(w, dtype=r_px.dtype)[None, :] - cx
    on_axis = r_px == 0
    safe_r = jnp.where(on_axis, 1.0, r_px)
    nx = jnp.where(on_axis, 1.0, dx / safe_r)
    ny = jnp.where(on_axis, 0.0, dy / safe_r)

    def inside(radius_px: Array) -> Array:
        safe_radius = jnp.maximum(radius_px, 1e-6)
        weight = curved_edge_coverage(r_px - safe_radius, nx, ny, 1.0 / safe_radius)
        weight = jnp.minimum(weight, math.pi * radius_px * radius_px)
        return jnp.sum(image * weight, axis=(-2, -1))

    # One radius at a time keeps memory at one image, not one per radius.
    sums = jax.lax.map(inside, r_out)  # (n_radii, *batch)
    sums = jnp.moveaxis(sums, 0, -1)
    norm = jnp.sum(image, axis=(-2, -1)) if total is None else as_float(total)
    fraction = sums / jnp.asarray(norm)[..., None]
    return fraction.reshape((*image.shape[:-2], *radii.shape))


# ------------------------------------------------------------------------------ tables


def _table_error(source: str, message: str) -> InputDataError:
    return InputDataError(f"{source}: {message}")


@dataclass(frozen=True, eq=False)
class RadialTable:
    """A tabulated 1-D glare function, ``(theta_deg, value)``, validated and callable.

    Calling it interpolates: in log-log (straight lines for power laws such as
    the CIE and Stiles–Holladay laws) when every angle and value is > 0,
    otherwise linearly. Below the first angle it holds the first value (a flat
    core); beyond the last angle it is 0 (no data, no light claimed).

    **Fields:**

    - `theta_deg`: strictly increasing angles ``>= 0`` in degrees.
    - `values`: finite values ``>= 0`` (sr⁻¹ for a GSF).
    - `source`: where the table came from, used in error messages.

    **Raises** on construction `InputDataError` naming the first offending index
    for: angles not strictly increasing, negative or non-finite angles, NaN /
    infinite / negative values, mismatched lengths, fewer than 2 rows.

    **Example:**

    ```python
    table = RadialTable([0.1, 1.0, 10.0], [1.2e4, 19.3, 0.06])
    table(jnp.array([0.3, 3.0]))
    ```
    """

    theta_deg: np.ndarray
    values: np.ndarray
    source: str = field(default="radial table")

    def __post_init__(self):
        src = self.source
        try:
            theta = np.asarray(self.theta_deg, dtype=np.float64)
            values = np.asarray(self.values, dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise _table_error(src, f"the table is not numeric ({e})") from e
        if theta.ndim != 1 or values.ndim != 1:
            raise _table_error(
                src,
                f"theta_deg and values must be 1-D, got shapes {theta.shape} and {values.shape}",
            )
        if theta.shape != values.shape:
            raise _table_error(
                src, f"theta_deg has {theta.size} entries but values has {values.size}"
            )
        if theta.size < 2:
            raise _table_error(src, f"a radial table needs at least 2 rows, got {theta.size}")
        bad = ~np.isfinite(theta)
        if bad.any():
            i = int(np.argmax(bad))
            raise _table_error(src, f"theta_deg[{i}] is {theta[i]}; expected finite angles")
        if theta[0] < 0:
            raise _table_error(src, f"theta_deg[0] = {theta[0]:g} deg is negative")
        step = np.diff(theta)
        if np.any(step <= 0):
            i = int(np.argmax(step <= 0)) + 1
            raise _table_error(
                src,
                f"theta_deg is not strictly increasing at index {i}: "
                f"{theta[i]:g} deg follows {theta[i - 1]:g} deg",
            )
        bad = ~np.isfinite(values)
        if bad.any():
            i = int(np.argmax(bad))
            raise _table_error(
                src, f"value[{i}] (at {theta[i]:g} deg) is {values[i]}; expected finite values"
            )
        if np.any(values < 0):
            i = int(np.argmax(values < 0))
            raise _table_error(
                src,
                f"value[{i}] (at {theta[i]:g} deg) is {values[i]:g}; expected values >= 0",
            )
        object.__setattr__(self, "theta_deg", theta)
        object.__setattr__(self, "values", values)

    @property
    def log_log(self) -> bool:
        """Whether interpolation is log-log (all angles and values > 0)."""
        return bool(self.theta_deg[0] > 0 and np.all(self.values > 0))

    def __call__(self, theta_deg: Float[ArrayLike, "*shape"]) -> Float[Array, "*shape"]:
        t = jnp.abs(as_float(theta_deg))
        xp = jnp.asarray(self.theta_deg, dtype=t.dtype)
        fp = jnp.asarray(self.values, dtype=t.dtype)
        if self.log_log:
            # Clamping first keeps log() finite at theta = 0, where the value is held anyway.
            q = jnp.maximum(t, xp[0])
            out = jnp.exp(jnp.interp(jnp.log(q), jnp.log(xp), jnp.log(fp)))
        else:
            out = jnp.interp(t, xp, fp)
        return jnp.where(t > xp[-1], 0.0, out)


# ------------------------------------------------------------------------------ GSF <-> PSF


GsfLike = Callable[[Array], Array] | RadialTable | tuple[ArrayLike, ArrayLike]


def _as_gsf(gsf: GsfLike) -> Callable[[Array], Array]:
    if isinstance(gsf, tuple):
        if len(gsf) != 2:
            raise InputDataError(
                f"a GSF table must be a (theta_deg, values) pair, got a tuple of {len(gsf)}"
            )
        return RadialTable(gsf[0], gsf[1])
    if callable(gsf):
        return gsf
    raise TypeError(
        "gsf must be a function of theta_deg, a RadialTable or a (theta_deg, values) pair; "
        f"got {type(gsf).__name__}"
    )


def _mean_over_subpixels(
    fn: Callable[[Array], Array], ty: Array, tx: Array, scale: Array, n: int
) -> Array:
    """Mean of ``fn(theta)`` over ``n × n`` midpoints of each pixel centred at (ty, tx).

    All sub-samples go to `fn` in one call (one array of shape ``(n², ny, nx)``), so
    a Python GSF runs once, not n² times.
    """
    offsets = jnp.asarray((np.arange(n) + 0.5) / n - 0.5)
    oy = jnp.repeat(offsets, n)[:, None, None]
    ox = jnp.tile(offsets, n)[:, None, None]
    yy = ty[None, :, None] + oy * scale
    xx = tx[None, None, :] + ox * scale
    return jnp.mean(fn(jnp.sqrt(yy * yy + xx * xx)), axis=0)


def gsf_to_psf(
    gsf: GsfLike,
    grid: AngularGrid,
    normalise: str = "none",
    *,
    oversample: int = 3,
    centre_oversample: int = 15,
    centre_radius_px: int = 3,
) -> Float[Array, "npix npix"]:
    """A 1-D glare spread function (sr⁻¹) as a 2-D PSF of energy per pixel on `grid`.

    Each pixel gets ``∫_pixel GSF(theta) dOmega``: the mean of the GSF over
    ``oversample × oversample`` sub-pixel midpoints times the pixel solid angle
    ``dtheta²`` (rad², small angles). Near the source, where GSFs are steep (the
    CIE core is 0.0046° wide), the pixels within `centre_radius_px` (a square
    patch) use ``centre_oversample²`` sub-samples instead. With the defaults the
    pixel integrals of a ``1 / theta²`` law are within ~0.2 % from 4 px out.

    **Normalisation** (`normalise`): ``"none"`` keeps ``GSF × dOmega``, so a
    unit-energy GSF gives the fraction of the light per pixel and the grid holds
    what falls inside it (the CIE function holds ~0.95 within 100°); ``"unit"``
    rescales the grid's sum to 1.

    **Arguments:**

    - `gsf`: a function of `theta_deg` (jnp array, deg) returning sr⁻¹; or a
      :class:`RadialTable`; or a ``(theta_deg, values)`` pair, validated as one.
      The function is called at every angle of the grid, 0 included: pass, e.g.,
      ``lambda t: cie_gsf(t, 70, 1.0, extrapolate=True)``.
    - `grid`: the output grid (source at pixel ``npix // 2``).
    - `normalise`: ``"none"`` or ``"unit"``.
    - `oversample`, `centre_oversample`, `centre_radius_px`: static integration
      settings (see above).

    **Returns:** ``(npix, npix)`` energy per pixel.

    **Raises:** `ConfigError` for an unknown `normalise`; `InputDataError` for an
    invalid table; `PhysicsRangeError` from the GSF itself (re-raised with the
    angular span of the grid).

    **Example:**

    ```python
    grid = AngularGrid(401, 0.01)
    psf = gsf_to_psf(lambda t: cie_gsf(t, 25.0, 0.5, extrapolate=True), grid)
    ```
    """
    if normalise not in NORMALISATIONS:
        raise ConfigError(f"normalise = {normalise!r} is unknown; expected one of {NORMALISATIONS}")
    for name, value in (
        ("oversample", oversample),
        ("centre_oversample", centre_oversample),
    ):
        if int(value) < 1:
            raise ValueError(f"{name} must be >= 1, got {value}")
    fn = _as_gsf(gsf)
    coords = grid.coords_deg()
    scale = grid.pixel_scale_deg
    try:
        image = _mean_over_subpixels(fn, coords, coords, scale, int(oversample))
        n = grid.npix
        c = n // 2
        lo = max(c - int(centre_radius_px), 0)
        hi = min(c + int(centre_radius_px) + 1, n)
        patch = _mean_over_subpixels(
            fn, coords[lo:hi], coords[lo:hi], scale, int(centre_oversample)
        )
    except PhysicsRangeError as e:
        span = float(grid.half_field_deg) * math.sqrt(2.0) if is_concrete(scale) else None
        where = f" (the grid spans 0-{span:.4g} deg)" if span is not None else ""
        raise PhysicsRangeError(
            f"{e}{where}; gsf_to_psf evaluates the GSF at every pixel, so wrap it to "
            "extrapolate, e.g. lambda t: cie_gsf(t, age, p, extrapolate=True)"
        ) from e
    image = image.at[lo:hi, lo:hi].set(patch)
    psf = image * grid.solid_angle_sr()
    if normalise == "unit":
        psf = psf / jnp.sum(psf)
    return psf


def psf_to_gsf(
    psf: Float[ArrayLike, "*batch h w"],
    pixel_scale_deg: Float[ArrayLike, ""],
    n_bins: int | None = None,
    max_angle_deg: Float[ArrayLike, ""] | None = None,
    centre: Float[ArrayLike, " 2"] | None = None,
) -> tuple[Float[Array, " n_bins"], Float[Array, "*batch n_bins"]]:
    """The radial GSF (sr⁻¹) of a PSF given as energy per pixel.

    The :func:`radial_profile` of the PSF divided by the pixel solid angle
    ``(pixel_scale_deg · pi / 180)²``. Arguments as in :func:`radial_profile`.

    **Returns:** ``(theta_deg, gsf)`` with the mean pixel distance of each annulus
    in degrees and the GSF in sr⁻¹.

    **Example:**

    ```python
    theta, gsf = psf_to_gsf(psf, 0.01)
    ```
    """
    theta, mean = radial_profile(psf, pixel_scale_deg, n_bins, max_angle_deg, centre)
    omega = (as_float(pixel_scale_deg) * (math.pi / 180.0)) ** 2
    return theta, mean / omega


# ------------------------------------------------------------------------------ files


@dataclass(frozen=True, eq=False)
class ReferenceImage:
    """A 2-D reference PSF read from an EXR file.

    **Fields:**

    - `psf`: float32 ``(H, W)`` (channel `Y`) or ``(H, W, C)`` pixels, as stored
      (energy per pixel for invglare's own PSFs).
    - `pixel_scale_deg`: degrees per pixel, from the `pixelScaleDeg` attribute.
    - `path`: the file.
    - `channels`, `wavelengths_nm`, `config`: as stored in the header (or None).
    """

    psf: np.ndarray
    pixel_scale_deg: float
    path: Path
    channels: tuple[str, ...] = ("Y",)
    wavelengths_nm: tuple[float, ...] | None = None
    config: dict[str, Any] | None = None


def _parse_table_text(path: Path, text: str) -> tuple[np.ndarray, np.ndarray]:
    rows: list[tuple[float, float]] = []
    header_allowed = True
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        parts = [p for p in line.replace(",", " ").replace(";", " ").split() if p]
        try:
            numbers = [float(p) for p in parts]
        except ValueError:
            if header_allowed:  # one header line of column names, e.g. "theta_deg,value"
                header_allowed = False
                continue
            raise InputDataError(
                f"{path}: line {lineno} is not numeric: {raw.strip()!r}; "
                "expected two columns theta_deg, value"
            ) from None
        header_allowed = False
        if len(numbers) != 2:
            raise InputDataError(
                f"{path}: line {lineno} has {len(numbers)} column(s): {raw.strip()!r}; "
                "expected two columns theta_deg, value"
            )
        rows.append((numbers[0], numbers[1]))
    if not rows:
        raise InputDataError(f"{path}: no data rows; expected two columns theta_deg, value")
    table = np.asarray(rows, dtype=np.float64)
    return table[:, 0], table[:, 1]


def load_reference_psf(path: str | os.PathLike[str]) -> ReferenceImage | RadialTable:
    """Read a reference PSF: a 2-D EXR image or a 1-D table of ``(theta_deg, value)``.

    - ``.exr``: read with `invglare.files.exr.read_exr`; the file must carry its
      pixel scale (`pixelScaleDeg`, degrees per pixel). Returns a
      :class:`ReferenceImage`.
    - ``.csv``, ``.txt``, ``.tsv``, ``.dat``: two numeric columns, angle in
      degrees and value (sr⁻¹ for a GSF), separated by commas, semicolons or
      white space; ``#`` starts a comment; one header line of column names is
      allowed. Returns a validated :class:`RadialTable`.

    **Raises:** `InputDataError` naming the file for: a missing or unreadable
    file, an unknown suffix, an EXR without `pixelScaleDeg`, any EXR problem
    `read_exr` reports, a malformed table line, non-increasing angles (with the
    index), NaN or negative values.

    **Example:**

    ```python
    ref = load_reference_psf("cie_age25.csv")   # lines of "theta_deg,value"
    grid_psf = gsf_to_psf(ref, AngularGrid(256, 0.01), normalise="unit")
    ```
    """
    src = Path(path)
    suffix = src.suffix.lower()
    if suffix == ".exr":
        return _read_reference_image(src)
    if suffix in TABLE_SUFFIXES:
        return _read_reference_table(src)
    raise InputDataError(
        f"{src}: unknown reference PSF format {suffix or '(no suffix)'!r}; expected .exr "
        f"(2-D) or one of {', '.join(TABLE_SUFFIXES)} (1-D table of theta_deg, value)"
    )


def _read_reference_image(src: Path) -> ReferenceImage:
    """A 2-D reference from an EXR (`read_exr` names a missing or broken file)."""
    from invglare.files.exr import read_exr

    image = read_exr(src)
    if image.pixel_scale_deg is None:
        raise InputDataError(
            f"{src}: the EXR header has no pixelScaleDeg attribute; a 2-D reference PSF "
            "needs its pixel scale in degrees per pixel (write it with "
            "invglare.files.write_exr(..., pixel_scale_deg=...))"
        )
    return ReferenceImage(
        psf=image.data,
        pixel_scale_deg=float(image.pixel_scale_deg),
        path=src,
        channels=image.channels,
        wavelengths_nm=image.wavelengths_nm,
        config=image.config,
    )


def _read_reference_table(src: Path) -> RadialTable:
    """A 1-D reference from a text table; a missing file or a folder is "not found"."""
    try:
        text = src.read_text(encoding="utf-8")
    except (FileNotFoundError, IsADirectoryError, NotADirectoryError):
        raise InputDataError(f"reference PSF file not found: {src}") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputDataError(f"{src}: cannot read the table ({e})") from e
    theta, values = _parse_table_text(src, text)
    return RadialTable(theta, values, source=str(src))
