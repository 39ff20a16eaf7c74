"""Shared test utilities: float64 context, finite-difference gradient checks, a toy PSF, a
small population of disk photos for batch fits."""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float


class GaussPSF(eqx.Module):
    """A unit-energy Gaussian PSF on an `npix` grid: a cheap model for fitting tests."""

    sigma_px: Float[Array, ""] = eqx.field(converter=jnp.asarray)
    npix: int = eqx.field(static=True, default=32)
    unused: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=0.0)  # no effect

    def __call__(self):
        c = self.npix // 2
        x = jnp.arange(self.npix, dtype=self.sigma_px.dtype) - c
        g = jnp.exp(-(x[None, :] ** 2 + x[:, None] ** 2) / (2 * self.sigma_px**2))
        return g / jnp.sum(g)


def x64():
    """Context manager enabling float64 for a gradient or precision test."""
    return jax.enable_x64(True)


def central_difference(f: Callable, x: float, eps: float = 1e-6) -> float:
    """Central finite difference of a scalar function of one scalar (run under `x64()`)."""
    return float((f(jnp.float64(x + eps)) - f(jnp.float64(x - eps))) / (2 * eps))


def assert_grad_matches_fd(
    f: Callable, x: float, eps: float = 1e-6, rtol: float = 1e-5, atol: float = 1e-10
) -> tuple[float, float]:
    """Assert autodiff d f/dx equals the central difference; returns (autodiff, fd)."""
    ad = float(jax.grad(f)(jnp.float64(x)))
    fd = central_difference(f, x, eps)
    np.testing.assert_allclose(ad, fd, rtol=rtol, atol=atol)
    return ad, fd


def assert_fd_converges(
    f: Callable, x: float, ad: float, eps: float, rtol: float = 1e-5, atol: float = 0.0
) -> tuple[float, float]:
    """Assert that central differences of `f` at `x` converge to the derivative `ad`.

    The differences are taken at two steps, `eps` and `eps / 2` (run under `x64()`). A
    right derivative passes both checks: the finer difference agrees with `ad` to `rtol`,
    and halving the step at least halves the discrepancy (truncation error falls as
    ``eps**2``, four times per halving) unless both are down at the floor of rounding. A
    wrong derivative keeps its discrepancy as the step shrinks.

    The floor is `atol` plus the rounding of the fine difference, ``8 * (float64
    epsilon) * |f(x)| / (eps / 2)`` (a few units in the last place of `f`, divided by the
    step). Choose `eps` so that truncation, not rounding, dominates where the function
    is smooth (about 1e-5 to 1e-4 of the parameter's scale).

    Returns the two differences (coarse, fine).
    """
    coarse = central_difference(f, x, eps)
    fine = central_difference(f, x, eps / 2)
    rounding = 8.0 * np.finfo(np.float64).eps * abs(float(f(jnp.float64(x)))) / (eps / 2)
    floor = atol + rounding
    np.testing.assert_allclose(ad, fine, rtol=rtol, atol=floor)
    err_coarse, err_fine = abs(coarse - ad), abs(fine - ad)
    assert err_fine <= 0.5 * err_coarse + floor, (
        f"central differences do not converge to {ad!r}: {coarse!r} at step {eps:g}, "
        f"{fine!r} at {eps / 2:g} (rounding floor {floor:.2g})"
    )
    return coarse, fine


def assert_grad_converges(
    f: Callable,
    x: float,
    eps: float,
    *,
    grad: float | None = None,
    shrink: float = 4.0,
    rtol: float = 1e-5,
    atol: float = 1e-10,
    err_msg: str = "",
) -> tuple[float, float, float]:
    """Assert autodiff d f/dx equals central differences at two steps, converging.

    The central difference at `eps` and at `eps / shrink` must each lie within
    ``atol + rtol * |d f/dx|`` of autodiff, and the differences must converge: the
    smaller step's truncation error is ``shrink²`` times smaller, so it must at least
    halve the larger step's error, unless there is no truncation left to see: the smaller
    step's error at the rounding floor, or both differences equal to it (f quadratic in
    x, or smooth beyond what the steps resolve). The floor is ``100 ulp * |f| / step``,
    the float64 rounding of f's values amplified by the division by the step (the noise
    measured on the veiling losses was about 6 ulp of f). Pick `eps` where truncation shows
    (around 1e-3 to 1e-4 of the value's scale) so that the check has something to see.

    `grad` is autodiff's value when the caller has it already (a shared compiled
    gradient); otherwise it is ``jax.grad(f)``. Run under `x64()`.
    Returns ``(autodiff, fd at eps, fd at eps / shrink)``.
    """
    ad = float(jax.grad(f)(jnp.float64(x))) if grad is None else float(grad)
    steps = (eps, eps / shrink)
    fds = [central_difference(f, x, h) for h in steps]
    errors = [abs(fd - ad) for fd in fds]
    tol = atol + rtol * abs(ad)
    value = abs(float(f(jnp.float64(x))))
    floor = 100 * np.finfo(np.float64).eps * value / steps[1]
    msg = (
        f"{err_msg}: autodiff {ad:.10g}, central differences {fds[0]:.10g} (step {steps[0]:.3g}), "
        f"{fds[1]:.10g} (step {steps[1]:.3g}); errors {errors[0]:.3g}, {errors[1]:.3g}, "
        f"tolerance {tol:.3g}, rounding floor {floor:.3g}"
    )
    assert errors[0] <= tol and errors[1] <= tol, msg
    converged = abs(fds[0] - fds[1]) <= floor
    assert errors[1] <= max(0.5 * errors[0], floor) or converged, "not converging: " + msg
    return ad, fds[0], fds[1]


# A population of small disk photos (pupils, fluxes, centres, noise of their own) and one
# fit config for them: `invglare fit-batch` tests and the batch benchmark's test.
DISK_MODEL = """
[model]
kind = "aperture"
focal_length_mm = 17.0
aperture_npix = 48
window_mm = 5.4

[[model.shapes]]
kind = "disk"
diameter_mm = 3.5

[output]
npix = 48
pixel_scale_deg = 0.0035

[spectrum]
wavelengths_nm = 550
"""

DISK_POPULATION = """
[synth]
model = "model.toml"
seed = 40
out = "crowd"

[population]
size = 4
seed = 11
name = "disk"

[population.set]
"model.aperture.shapes[0].diameter_mm" = ["uniform", 2.6, 3.6]

[population.observation]
flux = ["loguniform", 6e5, 2e6]
dx_px = ["uniform", -0.3, 0.3]
dy_px = ["uniform", -0.3, 0.3]

[observation]
background = 20.0
gain = 2.0
read_noise = 3.0
saturation = 30000.0
"""

DISK_FIT = """
[target]
file = "crowd/disk_00.exr"
saturation = 30000.0

[model]
config = "model.toml"

[observation]
gain = 2.0
read_noise = 3.0

[[free]]
path = "model.aperture.shapes[0].diameter_mm"
lower = 2.0
upper = 5.0

[[free]]
path = "obs.flux"
lower = 0.0
upper = inf

[[free]]
path = "obs.background"
lower = -100.0
upper = 1000.0

[[free]]
path = "obs.dx_px"
lower = -2.0
upper = 2.0

[[free]]
path = "obs.dy_px"
lower = -2.0
upper = 2.0

[solver]
n_starts = 2
max_steps = 60
"""




def disk_population(folder, size: int = 4):
    """Write model.toml, population.toml and fit.toml into `folder` and synthesise the
    photos crowd/disk_00.exr ... (with truths). **Returns:** `folder`."""
    from invglare.commands.synth import run_synth

    (folder / "model.toml").write_text(DISK_MODEL)
    (folder / "population.toml").write_text(DISK_POPULATION.replace("size = 4", f"size = {size}"))
    (folder / "fit.toml").write_text(DISK_FIT)
    run_synth([folder / "population.toml"])
    return folder
