"""Thin layers of the holographic eye and the propagation between them.

Each layer of Novosad & Ziegler's eye (sec. 2.2) is a thin element: a complex
transmission ``t(x, y)`` that multiplies the field at its plane. Between parallel planes
the field is carried by the band-limited angular spectrum (Matsushima & Shimobaba 2009),
:func:`invglare.optics.fresnel.angular_spectrum_kernel` (the kernel
:func:`invglare.optics.fresnel.angular_spectrum` uses), on the grid itself (periodic),
precomputed once per wavelength and reused by every iteration (`propagation_kernel`).

The transmissions here are pure phases (their modulus is 1, so they keep the field's
energy, Parseval):

- :func:`vergence_chirp`: a spherical wave's curvature, ``exp(i pi V r^2 / lambda)`` for a
  wave diverging from a point at distance ``1 / V``;
- :func:`thin_lens_phase`: a thin lens of power ``P`` (1/mm), ``exp(-i pi P r^2 / lambda)``;
- :func:`spectacle_phase`: a spectacle lens of sphere ``S`` and cylinder ``C`` (dioptres)
  with the cylinder's axis at ``axis_deg`` (minus- or plus-cylinder notation alike: the
  power is ``S`` along the axis and ``S + C`` across it);
- the tear film (:mod:`invglare.optics.holographic.tear_film`).

Amplitude layers (pupil, lids and lashes) come from :mod:`invglare.aperture.eye`.

**Sampling.** A phase ``phi`` is sampled when it changes by at most ``pi`` per pixel:
its local frequency ``|grad phi| / (2 pi)`` stays below ``1 / (2 pitch)``. For a quadratic
phase of power ``P`` out to radius ``r`` that is ``|P| r / lambda <= 1 / (2 pitch)``; on the
holographic grid (``pitch = lambda / (N dt)``) the wavelength drops out and the condition
reads ``|P| r <= N dt / 2``: the element must not bend rays at radius ``r`` beyond the
grid's half field (:func:`max_power_per_mm`).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Complex, Float

from invglare._core.checks import as_float, check_range
from invglare._core.grids import ApertureGrid, nm_to_mm
from invglare.optics.fresnel import angular_spectrum_kernel as propagation_kernel

__all__ = [
    "Spectacles",
    "max_power_per_mm",
    "propagate_periodic",
    "propagation_kernel",
    "radius_squared_mm2",
    "spectacle_phase",
    "thin_lens_phase",
    "vergence_chirp",
]


def radius_squared_mm2(grid: ApertureGrid) -> Float[Array, "n n"]:
    """``x^2 + y^2`` (mm^2) on a centred grid."""
    y, x = grid.mesh_mm()
    return x * x + y * y


def vergence_chirp(
    grid: ApertureGrid, wavelength_nm: ArrayLike, vergence_per_mm: ArrayLike
) -> Complex[Array, "n n"]:
    """``exp(i pi V r^2 / lambda)``: the curvature of a wave diverging from ``1 / V`` mm away.

    In the Fresnel approximation a point at distance ``z`` in front of the plane gives
    ``exp(i pi |x - X|^2 / (lambda z)) / z``: this factor times a plane wave of direction
    ``-X / z``. ``V > 0`` diverges (a near source), ``V = 0`` is a plane wave.
    """
    lam = nm_to_mm(wavelength_nm)
    # Separable, exp(a x^2) exp(a y^2): 2 n exponentials instead of n^2 (per vergence: an
    # array of vergences gives a chirp each, leading axes first).
    c = grid.coords_mm()
    a = math.pi * jnp.asarray(vergence_per_mm)[..., None] / lam
    along = jnp.exp(1j * a * (c * c))
    return along[..., :, None] * along[..., None, :]


def thin_lens_phase(
    grid: ApertureGrid, wavelength_nm: ArrayLike, power_per_mm: ArrayLike
) -> Complex[Array, "n n"]:
    """A thin lens of power `power_per_mm` (1/mm = D / 1000): ``exp(-i pi P r^2 / lambda)``."""
    return vergence_chirp(grid, wavelength_nm, -jnp.asarray(power_per_mm))


def spectacle_phase(
    grid: ApertureGrid,
    wavelength_nm: ArrayLike,
    sphere_d: ArrayLike,
    cylinder_d: ArrayLike = 0.0,
    axis_deg: ArrayLike = 0.0,
) -> Complex[Array, "n n"]:
    """A sphero-cylindrical spectacle lens: sphere `sphere_d`, cylinder `cylinder_d` (D).

    The power is `sphere_d` along the cylinder's axis (at `axis_deg` from +x,
    counter-clockwise) and ``sphere_d + cylinder_d`` across it:
    ``phi = -(pi / lambda) (S r^2 + C v^2)`` with ``v`` the distance from the axis line.
    """
    lam = nm_to_mm(wavelength_nm)
    y, x = grid.mesh_mm()
    a = jnp.deg2rad(jnp.asarray(axis_deg))
    v = -x * jnp.sin(a) + y * jnp.cos(a)
    s = jnp.asarray(sphere_d) * 1e-3
    c = jnp.asarray(cylinder_d) * 1e-3
    return jnp.exp(-1j * (math.pi / lam) * (s * (x * x + y * y) + c * v * v))


def max_power_per_mm(half_field_rad: float, radius_mm: float) -> float:
    """Largest lens power (1/mm) a grid samples out to `radius_mm`: ``half_field / radius``."""
    return half_field_rad / radius_mm


def propagate_periodic(
    field: Complex[Array, "*b n n"], kernel: Complex[Array, "n n"]
) -> Complex[Array, "*b n n"]:
    """Carry a field to the next plane: ``ifft2(fft2(field) * kernel)`` on its own grid.

    The kernel depends only on ``|f|``, so the field may be stored centred or with its
    origin at index 0: propagation commutes with the shift.
    """
    return jnp.fft.ifft2(jnp.fft.fft2(field) * kernel)


class Spectacles(eqx.Module):
    """A spectacle lens (the glasses layer the paper planned): sphere, cylinder, axis.

    **Fields:** `sphere_d`, `cylinder_d` (dioptres; the power is `sphere_d` along the
    axis and ``sphere_d + cylinder_d`` across it) and `axis_deg` (the cylinder's axis,
    from +x, counter-clockwise). A myope of ``-2 D`` wears ``sphere_d = -2``.
    """

    sphere_d: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)
    cylinder_d: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)
    axis_deg: Float[Array, ""] = eqx.field(converter=as_float, default=0.0)

    def __check_init__(self):
        for name in ("sphere_d", "cylinder_d", "axis_deg"):
            check_range(f"spectacles {name}", getattr(self, name), -math.inf)

    def transmission(self, grid: ApertureGrid, wavelength_nm: ArrayLike) -> Complex[Array, "n n"]:
        """The lens as a phase layer (:func:`spectacle_phase`)."""
        return spectacle_phase(grid, wavelength_nm, self.sphere_d, self.cylinder_d, self.axis_deg)

    def max_power_d(self) -> float:
        """The larger of the two principal powers in magnitude (D, concrete)."""
        s, c = float(self.sphere_d), float(self.cylinder_d)
        return max(abs(s), abs(s + c))
