"""Parametric veiling glare: ghosts as a Fourier series (Lee, *Parametric Veiling-Glare Rendering*).

Veiling glare is modelled as the sum of many weak, large, soft ghosts. Each ghost
is a radially symmetric profile with a centre, radius, peak intensity and edge
softness; the whole image is one truncated 2-D Fourier series over a period of
twice the screen (sec. 4.1), whose coefficients are summed over the ghosts
*before* any pixel is touched (sec. 4.3), then evaluated separably as two matrix
products (sec. 4.4), with sigma-factors against ringing (sec. 4.5-4.6). The
series machinery is in :mod:`invglare.models.veiling_series`; the ghosts come from
a :class:`~invglare.models.veiling_ghosts.GhostSet` (free parameters) or from a lens
prescription via paraxial matrix optics
(:class:`~invglare.models.veiling_ghosts.LensGhosts`, sec. 8).

**Decisions where the draft paper is open** (the code follows these):

- *Period* ``lam = 2 max(ny, nx) x pixel scale`` (``period_factor`` = 2). A ghost of
  support radius ``R`` (plus ~3 softness) centred at ``x_k`` leaves no periodic copy
  on the screen as long as ``|x_k| + R < lam - screen / 2`` on each axis
  (:meth:`VeilingGlare.wraps` checks it). Lens ghosts are often larger than the
  screen: a uniform disk that covers the whole screen is drawn with its radius cut
  to just beyond the screen, which changes nothing on it and keeps it from
  wrapping, and a ghost that does not touch the screen is not drawn
  (:meth:`VeilingGlare.drawn`). Large ghosts centred far off the screen that still
  reach onto it need a larger ``period_factor``.
- *Normalisation*: the coefficient integrals run over one period (eq. 39-40 are
  consistent with this; the ``[-lam, lam]`` limits of eq. 5 and 9 would double them).
- *Sigma factors*: ``sinc(n / (N + 1)) ** strength`` on each axis, the DC term kept
  (eq. 31 and 34 start their sums at 1, which would drop the mean, and ``sinc(n/N)``
  would zero the last computed harmonic). The strength is a differentiable
  parameter; 0 switches de-ringing off. A Fejér window is offered as well.
- *Positivity* (sec. 4.6 leaves it open): a truncated series of a non-negative
  image dips below zero next to sharp edges. Three measures, from the source out:
  soft edges (``softness_deg``) shrink the ringing where it starts; the sigma
  factors shrink what is left (with ``window="fejer"`` and an integer strength >= 1
  the series is provably non-negative, its kernel being non-negative); and
  ``positivity="clip"`` (default) floors the image at 0. The floor's gradient is 0
  where the series is negative, which only affects pixels that hold no light in
  the model; ``positivity="none"`` returns the raw series (linear in the
  intensities, e.g. for least squares with signed residuals).
- *Pixels*: the series is averaged over each pixel (a factor ``sinc(n w p / 2)`` per
  axis, free in the separable form), so the image holds energy per pixel rather
  than point samples; ``pixel_average=False`` gives point samples.
- *Ghost shapes* (sec. 5, 7.6): ``"disk"`` (uniform; closed form in Bessel J1),
  ``"hat"`` (the 2-D triangle: self-convolution of a disk; closed form in J1²) and
  ``"cosine"`` (raised cosine; Hankel transform by Gauss–Legendre quadrature),
  each with an optional Gaussian edge blur.

**Output.** Images are in **fraction of the source's flux per pixel**, the
normalisation of every invglare PSF: the glare spread function (sr⁻¹) times the
pixel's solid angle. The source's direct image is *not* included (it is the
other models' job, or a bright pixel in a scene); its share of the light is
:meth:`VeilingGlare.direct_fraction`.

**ISO 9358.** :meth:`VeilingGlare.veiling_glare_index` computes the veiling glare index as
the standard measures it: a uniformly bright field with a black spot on the axis, every
direction of the field sending its own ghosts to the spot's image. Lens ghosts move with
the light, so the glare spread function is not shift-invariant;
:meth:`VeilingGlare.veiling_glare_index_on_axis` (and :func:`veiling_glare_index` of any
one GSF) is the shift-invariant approximation, sec. 3's on-axis GSF standing for every
light; file headers carry both. For the bundled Cooke triplet the approximation is 3.3
times the standard's value (4.7e-4 against 1.45e-4 for a 0.5 deg spot).
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from invglare._core.checks import as_float, choose
from invglare.errors import ConfigError, PhysicsRangeError
from invglare.models.base import AbstractGlareModel, check_light_angle, check_no_state
from invglare.models.veiling_ghosts import GhostSet, LensGhosts, direction_of_screen_deg
from invglare.models.veiling_series import (
    PROFILES,
    WINDOWS,
    SeriesCoefficients,
    aggregate_coefficients,
    evaluate_separable,
    pixel_average_factors,
    sigma_factors,
)
from invglare.optics.paraxial import lens_to_table

__all__ = [
    "POSITIVITY",
    "GhostSet",
    "LensGhosts",
    "VeilingGlare",
    "veiling_glare_index",
]

#: How negative lobes of the series are handled.
POSITIVITY = ("clip", "none")
#: Radius (deg) of the black spot of the ISO 9358 veiling glare index in file headers.
VGI_SPOT_RADIUS_DEG = 0.5


def _screen_shape(npix) -> tuple[int, int]:
    values = (npix, npix) if isinstance(npix, int | np.integer) else tuple(npix)
    ok = len(values) == 2 and all(
        isinstance(v, int | np.integer) and not isinstance(v, bool) and v >= 2 for v in values
    )
    if not ok:
        raise ConfigError(f"npix must be an integer >= 2 or a pair (ny, nx) of them, got {npix!r}")
    return int(values[0]), int(values[1])


def _axis_deg(n: int, pixel_scale_deg: float) -> np.ndarray:
    """Pixel-centre coordinates (deg) of one axis; pixel ``n // 2`` is at 0."""
    return (np.arange(n) - n // 2) * pixel_scale_deg


class VeilingGlare(AbstractGlareModel):
    """Veiling-glare image of a light, from ghosts aggregated as one Fourier series.

    Build one with :meth:`build`. Call it with the light's direction to get the
    image; :meth:`batch` does many directions at once (animation).

    **Fields:**

    - `ghosts`: a :class:`GhostSet` or :class:`LensGhosts` (its arrays are parameters).
    - `sigma_strength`: de-ringing strength (>= 0; a parameter).
    - `light_angle_deg`: the light's direction ``(x, y)`` when a call gives none (a
      parameter: a fit of a photo finds where its light was; default on axis).
      Screen and directions share axes: see
      :mod:`invglare.models.veiling_ghosts` ("Screen coordinates").
    - `npix`: ``(ny, nx)`` screen size (static).
    - `pixel_scale_deg`: degrees per pixel (static).
    - `n_harmonics`: ``N``, the highest harmonic on each axis (static).
    - `profile`, `window`, `positivity`, `pixel_average`, `quadrature_nodes`, `chunk`:
      static choices, see :meth:`build`.
    """

    ghosts: GhostSet | LensGhosts
    sigma_strength: Float[Array, ""] = eqx.field(converter=as_float)
    npix: tuple[int, int] = eqx.field(static=True)
    pixel_scale_deg: float = eqx.field(static=True)
    n_harmonics: int = eqx.field(static=True)
    profile: str = eqx.field(static=True, default="disk")
    window: str = eqx.field(static=True, default="lanczos")
    positivity: str = eqx.field(static=True, default="clip")
    pixel_average: bool = eqx.field(static=True, default=True)
    quadrature_nodes: int = eqx.field(static=True, default=48)
    chunk: int | None = eqx.field(static=True, default=None)
    period_factor: float = eqx.field(static=True, default=2.0)
    light_angle_deg: Float[Array, " 2"] = eqx.field(converter=as_float, default=(0.0, 0.0))
    centre: ClassVar[str] = "axis"
    animated: ClassVar[bool] = False

    def __check_init__(self):
        if not isinstance(self.ghosts, GhostSet | LensGhosts):
            raise ConfigError(
                "ghosts must be a GhostSet or LensGhosts, got " + type(self.ghosts).__name__
            )
        choose("profile", self.profile, PROFILES)
        choose("window", self.window, WINDOWS)
        choose("positivity", self.positivity, POSITIVITY)
        if not isinstance(self.sigma_strength, jax.core.Tracer):
            s = np.asarray(self.sigma_strength, dtype=float)
            if s.shape != () or not np.isfinite(s) or s < 0:
                raise PhysicsRangeError(f"sigma_strength must be a number >= 0, got {s}")
        check_light_angle(self.light_angle_deg)

    @classmethod
    def build(
        cls,
        ghosts: GhostSet | LensGhosts,
        *,
        npix: int | tuple[int, int] = 256,
        pixel_scale_deg: float = 0.1,
        n_harmonics: int = 64,
        profile: str = "disk",
        sigma_strength: float = 1.0,
        window: str = "lanczos",
        positivity: str = "clip",
        pixel_average: bool = True,
        quadrature_nodes: int = 48,
        chunk: int | None = None,
        period_factor: float = 2.0,
        light_angle_deg: Float[ArrayLike, " 2"] = (0.0, 0.0),
    ) -> VeilingGlare:
        """Validate every choice and build the model.

        **Arguments:**

        - `ghosts`: :class:`GhostSet` (free parameters) or :class:`LensGhosts` (lens).
        - `npix`: screen size, one integer (square) or ``(ny, nx)``.
        - `pixel_scale_deg`: degrees of field per pixel.
        - `n_harmonics`: ``N``; features down to ``period / (2 N)`` are resolved, i.e.
          ``max(ny, nx) / N`` pixels.
        - `profile`: ghost shape, ``"disk"``, ``"hat"`` or ``"cosine"``.
        - `sigma_strength`: exponent of the sigma factors (0: none, 1: Lanczos).
        - `window`: ``"lanczos"`` or ``"fejer"`` (see
          :func:`~invglare.models.veiling_series.sigma_factors`).
        - `positivity`: ``"clip"`` (floor at 0) or ``"none"``.
        - `pixel_average`: average the series over each pixel (default) or sample it.
        - `quadrature_nodes`: Gauss–Legendre nodes for the ``"cosine"`` profile.
        - `chunk`: ghosts per aggregation step (default: bounded memory).
        - `period_factor`: period of the series in units of the larger screen side
          (2 in the paper; more keeps large off-screen ghosts from wrapping round, at
          the cost of resolution for a given `n_harmonics`).
        - `light_angle_deg`: the light's direction ``(x, y)`` (deg) for calls without one.

        **Example:**

        ```python
        ghosts = GhostSet.build([[0.0, 0.0], [2.0, 1.0]], [3.0, 5.0], [0.01, 0.002],
                                softness_deg=0.1)
        model = VeilingGlare.build(ghosts, npix=256, pixel_scale_deg=0.05, n_harmonics=64)
        image = model(jnp.array([4.0, -2.0]))    # (256, 256), fraction of flux per pixel
        ```
        """
        shape = _screen_shape(npix)
        if isinstance(n_harmonics, bool) or not isinstance(n_harmonics, int | np.integer):
            raise ConfigError(f"n_harmonics must be an integer >= 1, got {n_harmonics!r}")
        if n_harmonics < 1:
            raise ConfigError(f"n_harmonics must be an integer >= 1, got {n_harmonics}")
        scale = float(pixel_scale_deg)
        if not (math.isfinite(scale) and scale > 0):
            raise PhysicsRangeError(f"pixel_scale_deg must be > 0 deg, got {pixel_scale_deg!r}")
        if isinstance(quadrature_nodes, bool) or not isinstance(quadrature_nodes, int):
            raise ConfigError(f"quadrature_nodes must be an integer >= 4, got {quadrature_nodes!r}")
        if quadrature_nodes < 4:
            raise ConfigError(f"quadrature_nodes must be an integer >= 4, got {quadrature_nodes}")
        if chunk is not None and (not isinstance(chunk, int) or chunk < 1):
            raise ConfigError(f"chunk must be a positive integer or None, got {chunk!r}")
        if not (isinstance(period_factor, int | float) and period_factor >= 1.0):
            raise ConfigError(f"period_factor must be a number >= 1, got {period_factor!r}")
        return cls(
            ghosts=ghosts,
            sigma_strength=sigma_strength,
            npix=shape,
            pixel_scale_deg=scale,
            n_harmonics=int(n_harmonics),
            profile=choose("profile", profile, PROFILES),
            window=choose("window", window, WINDOWS),
            positivity=choose("positivity", positivity, POSITIVITY),
            pixel_average=bool(pixel_average),
            quadrature_nodes=int(quadrature_nodes),
            chunk=chunk,
            period_factor=float(period_factor),
            light_angle_deg=light_angle_deg,
        )

    # ----------------------------------------------------------------------------- geometry

    @property
    def period_deg(self) -> float:
        """The series period: `period_factor` (2, sec. 4.1) times the larger screen side (deg)."""
        return self.period_factor * max(self.npix) * self.pixel_scale_deg

    @property
    def pixel_solid_angle_sr(self) -> float:
        """Solid angle of one pixel (sr, small-angle)."""
        return math.radians(self.pixel_scale_deg) ** 2

    def coords_deg(self) -> tuple[Float[Array, " nx"], Float[Array, " ny"]]:
        """Pixel-centre coordinates ``(x, y)`` of the columns and rows (deg)."""
        ny, nx = self.npix
        return (
            jnp.asarray(_axis_deg(nx, self.pixel_scale_deg)),
            jnp.asarray(_axis_deg(ny, self.pixel_scale_deg)),
        )

    def weights(self) -> Float[Array, " N1"]:
        """Per-harmonic weights on each axis: sigma factors times pixel averaging."""
        w = sigma_factors(self.n_harmonics, self.sigma_strength, self.window)
        if self.pixel_average:
            w = w * pixel_average_factors(self.n_harmonics, self.pixel_scale_deg, self.period_deg)
        return w

    # ----------------------------------------------------------------------------- outputs

    def _angle(self, light_angle_deg: Float[ArrayLike, " 2"] | None) -> Float[Array, " 2"]:
        return self.light_angle_deg if light_angle_deg is None else as_float(light_angle_deg)

    def ghosts_at(self, light_angle_deg: Float[ArrayLike, " 2"] | None = None) -> GhostSet:
        """The ghosts (positions, radii, intensities) for a light at `light_angle_deg`."""
        angle = self._angle(light_angle_deg)
        check_light_angle(angle)
        return self.ghosts.at(angle, self.profile)

    def drawn(self, ghosts: GhostSet) -> tuple[Float[Array, " K"], Float[Array, " K"]]:
        """Intensities and radii the series draws, so that only what is on the screen counts.

        - A ghost whose reach (radius plus four softness widths and a pixel) does not
          touch the screen gets intensity 0: it is invisible, and drawn it could
          reach the screen round the period.
        - A ``"disk"`` ghost larger than the distance from its centre to the farthest
          screen corner (plus the same margin) looks the same on the screen with its
          radius cut to anything between that distance and the nearest periodic copy
          of the screen; it is cut halfway between the two, where the ringing of its
          edge reaches the screen least. Other profiles change inside with the
          radius, so they keep theirs.
        """
        ny, nx = self.npix
        dtype = ghosts.radius_deg.dtype
        half = 0.5 * self.pixel_scale_deg * jnp.asarray([nx, ny], dtype=dtype)
        margin = 4.0 * ghosts.softness_deg + self.pixel_scale_deg
        outside = jnp.maximum(jnp.abs(ghosts.position_deg) - half, 0.0)
        near = jnp.sqrt(jnp.sum(outside**2, axis=-1))
        intensity = jnp.where(near < ghosts.radius_deg + margin, ghosts.intensity_per_sr, 0.0)
        if self.profile != "disk":
            return intensity, ghosts.radius_deg
        corner = jnp.sqrt(jnp.sum((jnp.abs(ghosts.position_deg) + half) ** 2, axis=-1))
        cover = corner + margin
        # Put the cut edge halfway between the screen and its nearest periodic copy, as
        # far from both as it can be: the edge's residual ringing is smallest there.
        limit = jnp.min(self.period_deg - half - jnp.abs(ghosts.position_deg), axis=-1) - margin
        cut = jnp.maximum(cover, 0.5 * (cover + limit))
        return intensity, jnp.minimum(ghosts.radius_deg, cut)

    def wraps(self, light_angle_deg: Float[ArrayLike, " 2"] | None = None) -> Array:
        """Which drawn ghosts reach the screen again through the periodicity (``(K,)`` bool).

        A visible ghost of drawn radius ``R`` and softness ``s`` centred at ``c`` stays
        off the screen's periodic copies when ``|c| + R + 3 s < period - screen / 2``
        on both axes. Ghosts flagged here are drawn wrongly: keep them smaller or
        enlarge the period (`period_factor`).
        """
        g = self.ghosts_at(light_angle_deg)
        ny, nx = self.npix
        half = 0.5 * self.pixel_scale_deg * jnp.asarray([nx, ny], dtype=g.radius_deg.dtype)
        intensity, radius = self.drawn(g)
        reach = (radius + 3.0 * g.softness_deg)[:, None]
        beyond = jnp.any(jnp.abs(g.position_deg) + reach > self.period_deg - half, axis=-1)
        return beyond & (intensity > 0)

    def coefficients(
        self, light_angle_deg: Float[ArrayLike, " 2"] | None = None
    ) -> SeriesCoefficients:
        """Aggregated series coefficients (sr⁻¹) for a light at `light_angle_deg` (eq. 20-23).

        The only step whose cost grows with the number of ghosts.
        """
        g = self.ghosts_at(light_angle_deg)
        intensity, radius = self.drawn(g)
        return aggregate_coefficients(
            self.profile,
            intensity,
            radius,
            g.softness_deg,
            g.position_deg,
            self.n_harmonics,
            self.period_deg,
            self.quadrature_nodes,
            self.chunk,
        )

    def _gsf(self, angle: Array) -> Float[Array, "ny nx"]:
        x, y = self.coords_deg()
        w = self.weights().astype(x.dtype)
        return evaluate_separable(self.coefficients(angle), x, y, self.period_deg, w, w)

    def _image(self, angle: Array) -> Float[Array, "ny nx"]:
        image = self._gsf(angle) * self.pixel_solid_angle_sr
        if self.positivity == "clip":
            image = jnp.maximum(image, 0.0)
        return image

    def gsf(self, light_angle_deg: Float[ArrayLike, " 2"] | None = None) -> Float[Array, "ny nx"]:
        """The glare spread function on the screen (sr⁻¹), before the positivity floor."""
        angle = self._angle(light_angle_deg)
        check_light_angle(angle)
        return _jitted_gsf(self, angle)

    def __call__(
        self, light_angle_deg: Float[ArrayLike, " 2"] | None = None, *, state: Any = None
    ) -> Float[Array, "ny nx"]:
        """Veiling-glare image for a light at `light_angle_deg` = (x, y) deg.

        Without an angle, the light is at the model's own `light_angle_deg` (the leaf a
        fit adjusts).

        **Returns:** ``(ny, nx)``, fraction of the light's flux per pixel, with the
        optical axis at pixel ``(ny // 2, nx // 2)``, x growing with the column and y
        with the row (down the frame as image files show it); the light's direct image
        would sit at :func:`~invglare.models.veiling_ghosts.screen_position_deg` of its
        direction (not drawn).

        **Example:**

        ```python
        image = model(jnp.array([3.0, 1.0]))
        ```
        """
        angle = self._angle(light_angle_deg)
        check_light_angle(angle)
        check_no_state(self, state)
        # Validated here, where values are concrete; the work is one compiled program
        # (inlined when the caller is itself jitted).
        return _jitted_image(self, angle)

    def batch(
        self, light_angles_deg: Float[ArrayLike, "K 2"], batch_size: int | None = None
    ) -> Float[Array, "K ny nx"]:
        """Images for many light directions (``vmap``; `batch_size` at a time if given).

        **Example:**

        ```python
        path = jnp.stack([jnp.linspace(-10, 10, 48), jnp.zeros(48)], axis=-1)
        frames = eqx.filter_jit(model.batch)(path)   # (48, ny, nx)
        ```
        """
        angles = as_float(light_angles_deg)
        check_light_angle(angles, batched=True)
        if batch_size is None:
            return jax.vmap(self._image)(angles)
        return jax.lax.map(self._image, angles, batch_size=int(batch_size))

    def direct_fraction(self, light_angle_deg: Float[ArrayLike, " 2"] | None = None) -> Array:
        """Share of the light in the source's direct image (not part of the image)."""
        return self.ghosts.direct_fraction(self._angle(light_angle_deg))

    def centre_value(self, light_angle_deg: Float[ArrayLike, " 2"] | None = None) -> Array:
        """The image's value at the screen's centre pixel (the axis) for a light at the angle.

        The pixel ``(ny // 2, nx // 2)`` of :meth:`__call__`'s image, from the series at
        that one point (``O(K N^2)``, no screen evaluated).
        """
        angle = self._angle(light_angle_deg)
        check_light_angle(angle)
        return _jitted_centre(self, angle)

    def _centre(self, angle: Array) -> Array:
        dtype = self.ghosts_at(angle).radius_deg.dtype
        origin = jnp.zeros(1, dtype)
        w = self.weights().astype(dtype)
        value = evaluate_separable(self.coefficients(angle), origin, origin, self.period_deg, w, w)
        value = value[0, 0] * self.pixel_solid_angle_sr
        return jnp.maximum(value, 0.0) if self.positivity == "clip" else value

    def veiling_glare_index(
        self,
        spot_radius_deg: float,
        field_radius_deg: float | None = None,
        *,
        step_px: int | None = None,
        batch_size: int = 128,
    ) -> Float[Array, ""]:
        """ISO 9358 veiling glare index as the standard measures it: light from every direction.

        ISO 9358 images a uniformly bright field with a black spot on the axis and divides
        the light in the spot's image by the light there with the spot removed. Every
        direction of the field sends its own ghosts, so the glare at the axis is the sum
        over directions ``d`` of the field of :meth:`centre_value` ``(d)``::

            VGI = sum_{spot < |s(d)| <= field} v(d) / (T(0) + sum_{|s(d)| <= field} v(d)),

        ``s(d)`` the screen position of a direction's direct image (one screen pixel per
        direction: :func:`~invglare.models.veiling_ghosts.direction_of_screen_deg` of the
        pixel), ``v(d)`` the glare it sends to the centre pixel, ``T(0)`` the direct
        fraction on the axis. Each screen pixel's worth of directions counts alike (the
        paraxial model's flux per direction; the ``cos^4`` fall-off of a real field is
        neglected, as in the ghost energies). Ghosts that move with the light (every
        lens ghost) make this differ from :meth:`veiling_glare_index_on_axis`, the
        shift-invariant approximation.

        **Arguments:**

        - `spot_radius_deg`, `field_radius_deg`: as for :func:`veiling_glare_index`
          (screen degrees; ``None``: the whole screen is the field).
        - `step_px`: the field is sampled one direction per ``step_px x step_px`` block of
          screen pixels (each standing for its block), the spot one direction per pixel;
          1 is the brute-force sum over every pixel. Default: the smallest step that keeps
          the field to about 512 directions (for the bundled Cooke, step 14; steps 16 and
          7 agree to 0.06 %: each ghost changes slowly with the light's direction).
        - `batch_size`: directions evaluated at once (memory).

        **Example:**

        ```python
        vgi = model.veiling_glare_index(spot_radius_deg=0.5)          # ISO 9358
        approx = model.veiling_glare_index_on_axis(spot_radius_deg=0.5)
        ```
        """
        ny, nx = self.npix
        if step_px is None:
            step_px = max(1, math.ceil(math.sqrt(ny * nx / 512.0)))
        if isinstance(step_px, bool) or not isinstance(step_px, int | np.integer) or step_px < 1:
            raise ConfigError(f"step_px must be an integer >= 1, got {step_px!r}")
        radii = (("spot_radius_deg", spot_radius_deg), ("field_radius_deg", field_radius_deg))
        for name, value in radii:
            if value is not None and not (math.isfinite(float(value)) and float(value) >= 0):
                raise PhysicsRangeError(f"{name} must be a number >= 0 deg, got {value!r}")
        scale = self.pixel_scale_deg
        rows = np.arange(ny) - ny // 2
        cols = np.arange(nx) - nx // 2
        distance = np.hypot(rows[:, None], cols[None, :])
        spot = np.clip(spot_radius_deg / scale - distance + 0.5, 0.0, 1.0)
        field = (
            np.ones_like(distance)
            if field_radius_deg is None
            else np.clip(field_radius_deg / scale - distance + 0.5, 0.0, 1.0)
        )
        field = np.maximum(field, spot)
        # The field: one direction per block, at its pixels' mean position, weighted by
        # the block's field coverage.
        block = (rows[:, None] // step_px + ny) * (nx + 1) + (cols[None, :] // step_px + nx)
        _, index = np.unique(block.ravel(), return_inverse=True)
        count = np.bincount(index)
        weight = np.bincount(index, field.ravel())
        yy = np.broadcast_to(rows[:, None], distance.shape).ravel()
        xx = np.broadcast_to(cols[None, :], distance.shape).ravel()
        centres = np.stack([np.bincount(index, xx) / count, np.bincount(index, yy) / count], -1)
        keep = weight > 0
        # The spot: every pixel it touches, one direction each.
        touched = spot.ravel() > 0
        spot_xy = np.stack([xx[touched], yy[touched]], -1)
        xy = np.concatenate([centres[keep], spot_xy]) * scale
        dtype = self.ghosts_at(None).radius_deg.dtype
        # Padded to whole batches (of the axis, weight 0): fewer shapes to compile.
        batch = max(1, int(batch_size))
        padded = np.zeros((-(-xy.shape[0] // batch) * batch, 2))
        padded[: xy.shape[0]] = xy
        angles = direction_of_screen_deg(jnp.asarray(padded, dtype=dtype))
        values = _centre_values(self, angles, batch)[: xy.shape[0]]
        n_field = int(np.sum(keep))
        total = jnp.sum(values[:n_field] * jnp.asarray(weight[keep], values.dtype))
        in_spot = jnp.sum(values[n_field:] * jnp.asarray(spot.ravel()[touched], values.dtype))
        direct = self.direct_fraction(jnp.zeros(2, values.dtype))
        return (total - in_spot) / (direct + total)

    def veiling_glare_index_on_axis(
        self, spot_radius_deg: float, field_radius_deg: float | None = None
    ) -> Float[Array, ""]:
        """The veiling glare index from the on-axis GSF alone: the shift-invariant approximation.

        :func:`veiling_glare_index` of the image of a light on the axis (sec. 3's GSF
        standing for every light in the field). It equals :meth:`veiling_glare_index`
        when every ghost keeps its offset from the light's direct image (a
        :class:`GhostSet` with ``ratio = 1``, in a field symmetric about the axis); lens
        ghosts move at their own rates, and for the bundled Cooke this is 3.3 times the
        standard's measure.

        **Example:**

        ```python
        approx = model.veiling_glare_index_on_axis(spot_radius_deg=0.5)
        ```
        """
        on_axis = (0.0, 0.0)
        return veiling_glare_index(
            self(on_axis),
            self.pixel_scale_deg,
            spot_radius_deg,
            field_radius_deg,
            direct_fraction=self.direct_fraction(on_axis),
        )

    # ------------------------------------------------------------------ the model interface

    @property
    def wavelengths_nm(self) -> None:
        """None: ghosts are drawn without a wavelength."""
        return None

    @property
    def shift_invariant(self) -> bool:
        """False: each light direction has its own ghosts."""
        return False

    def core_radius_px(self) -> None:
        return None  # the light's direct image is not drawn

    def header(self) -> dict[str, Any]:
        return {
            "psfNormalisation": "fraction of the light's flux per pixel (veiling glare only)",
            "veilingGlareIndex": float(self.veiling_glare_index(VGI_SPOT_RADIUS_DEG)),
            "veilingGlareIndexOnAxisGSF": float(
                self.veiling_glare_index_on_axis(VGI_SPOT_RADIUS_DEG)
            ),
            "vgiSpotRadiusDeg": VGI_SPOT_RADIUS_DEG,
        }

    def sized_for(self, others) -> VeilingGlare:
        return self  # no raster structure

    def to_config(self) -> dict[str, Any]:
        """The config of this model, every choice explicit (lenses written inline).

        ``build_model(model.to_config())`` rebuilds the same model.
        """
        table: dict[str, Any] = {
            "kind": "veiling",
            "profile": self.profile,
            "n_harmonics": self.n_harmonics,
            "sigma_strength": float(self.sigma_strength),
            "window": self.window,
            "positivity": self.positivity,
            "pixel_average": self.pixel_average,
            "quadrature_nodes": self.quadrature_nodes,
            "period_factor": self.period_factor,
            "light_angle_deg": np.asarray(self.light_angle_deg, dtype=float).tolist(),
        }
        source = self.ghosts
        if isinstance(source, GhostSet):
            table["ghosts"] = {
                "position_deg": np.asarray(source.position_deg, dtype=float).tolist(),
                "radius_deg": np.asarray(source.radius_deg, dtype=float).tolist(),
                "intensity_per_sr": np.asarray(source.intensity_per_sr, dtype=float).tolist(),
                "softness_deg": np.asarray(source.softness_deg, dtype=float).tolist(),
                "ratio": np.asarray(source.ratio, dtype=float).tolist(),
                "transmission": float(source.transmission),
            }
        else:
            table["lens"] = {
                "max_reflections": source.max_reflections,
                "softness_deg": float(source.softness_deg),
                "min_radius_deg": float(source.min_radius_deg),
                **lens_to_table(source.lens),
            }
        ny, nx = self.npix
        return {
            "model": table,
            "output": {
                "npix": ny if ny == nx else [ny, nx],
                "pixel_scale_deg": self.pixel_scale_deg,
            },
        }


@eqx.filter_jit
def _jitted_gsf(model: VeilingGlare, angle: Array) -> Array:
    return model._gsf(angle)


@eqx.filter_jit
def _jitted_image(model: VeilingGlare, angle: Array) -> Array:
    return model._image(angle)


@eqx.filter_jit
def _jitted_centre(model: VeilingGlare, angle: Array) -> Array:
    return model._centre(angle)


@eqx.filter_jit
def _centre_values(model: VeilingGlare, angles: Array, batch_size: int) -> Array:
    return jax.lax.map(model._centre, angles, batch_size=batch_size)


def _disk_weight(distance_px: Array, radius_px) -> Array:
    """Approximate pixel coverage of a disk: a one-pixel linear ramp across its edge."""
    return jnp.clip(radius_px - distance_px + 0.5, 0.0, 1.0)


def veiling_glare_index(
    gsf: Float[ArrayLike, "ny nx"],
    pixel_scale_deg: float,
    spot_radius_deg: Float[ArrayLike, ""],
    field_radius_deg: Float[ArrayLike, ""] | None = None,
    direct_fraction: Float[ArrayLike, ""] = 1.0,
    centre_px: tuple[float, float] | None = None,
) -> Float[Array, ""]:
    """Veiling glare index (ISO 9358) from a glare spread function.

    ISO 9358 images a uniform bright field with a small black spot in it; the
    index is the illuminance in the spot's image divided by the illuminance there
    with the spot removed. If the glare spread function is shift-invariant, each
    point of the field sends ``GSF(p)`` to the spot's centre from the offset ``p``,
    so (the spot's own image being black)::

        VGI = sum_{spot < |p| <= field} G(p) / (T + sum_{|p| <= field} G(p)),

    with ``G`` the glare per pixel (fraction of the source's flux) and ``T`` the
    share of the light in the direct image.

    **Arguments:**

    - `gsf`: ``(ny, nx)`` glare only (no direct image), fraction of the source's flux
      per pixel, the source at `centre_px` — what :class:`VeilingGlare` returns.
    - `pixel_scale_deg`: degrees per pixel.
    - `spot_radius_deg`: angular radius of the black spot (deg).
    - `field_radius_deg`: angular radius of the bright field (deg); ``None``: the
      whole image.
    - `direct_fraction`: ``T`` (1 if the GSF is normalised to the direct image).
    - `centre_px`: ``(row, col)`` of the source (default ``(ny // 2, nx // 2)``).

    **Returns:** the index as a fraction (multiply by 100 for per cent).

    Pixels on the circles count by a linear coverage ramp one pixel wide, so the
    index is differentiable in the image and the radii.

    **Example:**

    ```python
    vgi = veiling_glare_index(model(), model.pixel_scale_deg, spot_radius_deg=0.5,
                              direct_fraction=model.direct_fraction())
    ```
    """
    g = as_float(gsf)
    if g.ndim != 2:
        raise PhysicsRangeError(f"gsf must be a 2-D image, got shape {g.shape}")
    scale = float(pixel_scale_deg)
    if not (math.isfinite(scale) and scale > 0):
        raise PhysicsRangeError(f"pixel_scale_deg must be > 0 deg, got {pixel_scale_deg!r}")
    for name, value in (
        ("spot_radius_deg", spot_radius_deg),
        ("field_radius_deg", field_radius_deg),
    ):
        if value is not None and not isinstance(value, jax.core.Tracer):
            v = np.asarray(value, dtype=float)
            if v.shape != () or not np.isfinite(v) or v < 0:
                raise PhysicsRangeError(f"{name} must be a number >= 0 deg, got {v}")
    ny, nx = g.shape
    cy, cx = (ny // 2, nx // 2) if centre_px is None else centre_px
    rows = jnp.arange(ny, dtype=g.dtype)[:, None] - cy
    cols = jnp.arange(nx, dtype=g.dtype)[None, :] - cx
    distance = jnp.sqrt(rows**2 + cols**2)
    spot = _disk_weight(distance, as_float(spot_radius_deg) / scale)
    field = (
        jnp.ones_like(g)
        if field_radius_deg is None
        else _disk_weight(distance, as_float(field_radius_deg) / scale)
    )
    field = jnp.maximum(field, spot)  # a spot larger than the field: the field is the spot
    veiled = jnp.sum(g * (field - spot))
    return veiled / (as_float(direct_fraction) + jnp.sum(g * field))
