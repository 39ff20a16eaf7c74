"""Empirical straylight references: the CIE glare spread function and its relatives.

All three functions give the equivalent veiling luminance per unit glare
illuminance, ``L_eq / E_gl`` in (cd/m²)/lx, which is sr⁻¹: read as a PSF, it is
the fraction of the light from a point source that lands per steradian at an
angle `theta_deg` from the source. Angles are in **degrees** throughout.

- :func:`cie_gsf`: the CIE general disability glare equation (CIE 135/1-1999,
  "Disability glare", Vos & van den Berg; retained in CIE 180:2010), with age
  and ocular pigmentation.
- :func:`stiles_holladay`: the classical ``10 / theta²`` law and the CIE's
  age-adjusted form ``10 [1 + (A / 62.5)^4] / theta²``.
- :func:`spencer_1995_psf`: the photopic point-spread function of Spencer,
  Shirley, Zimmerman & Greenberg (SIGGRAPH 1995).

Range checks run on concrete inputs only: under `jit` (a traced age in a fit,
say) nothing is checked, so validate at the public boundary.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from invglare._core.checks import as_float, is_concrete
from invglare.errors import PhysicsRangeError

__all__ = [
    "AGE_RANGE_YEARS",
    "CIE_GSF_RANGE_DEG",
    "PIGMENTATION_RANGE",
    "SPENCER_PHOTOPIC_WEIGHTS",
    "STILES_HOLLADAY_RANGE_DEG",
    "cie_gsf",
    "spencer_1995_psf",
    "stiles_holladay",
]

#: Stated validity of the CIE general disability glare equation (deg).
CIE_GSF_RANGE_DEG = (0.1, 100.0)
#: Stated validity of the (age-adjusted) Stiles–Holladay law (deg).
STILES_HOLLADAY_RANGE_DEG = (1.0, 30.0)
#: Ages accepted (years). The CIE data cover roughly 20-80; the formula is smooth beyond.
AGE_RANGE_YEARS = (0.0, 100.0)
#: Pigmentation factors accepted: 0 very dark (black) eyes, 0.5 brown-eyed Caucasians,
#: 1.0 blue-green-eyed Caucasians; up to 1.2 for very light (albinotic-leaning) eyes.
PIGMENTATION_RANGE = (0.0, 1.2)
#: Weights of Spencer et al.'s photopic PSF on its three terms (f0, f1, f2).
SPENCER_PHOTOPIC_WEIGHTS = (0.384, 0.478, 0.138)


def _check_interval(name: str, value, lo: float, hi: float, unit: str, hint: str = "") -> None:
    """Raise `PhysicsRangeError` naming the first element of concrete `value` outside [lo, hi]."""
    if not is_concrete(value):
        return
    arr = np.atleast_1d(np.asarray(value, dtype=float))
    bad = ~np.isfinite(arr) | (arr < lo) | (arr > hi)
    if bad.any():
        first = arr[bad][0]
        where = "" if arr.size == 1 else f" (element {int(np.argmax(bad))} of {arr.size})"
        suffix = f" {unit}" if unit else ""
        raise PhysicsRangeError(
            f"{name} = {first:g}{suffix}{where} is outside the accepted range "
            f"{lo:g}-{hi:g}{suffix}{hint}"
        )


def _check_angles(name: str, theta, lo: float, hi: float, what: str, extrapolate: bool) -> None:
    if not is_concrete(theta):
        return
    arr = np.atleast_1d(np.asarray(theta, dtype=float))
    if not np.all(np.isfinite(arr)):
        bad = int(np.argmax(~np.isfinite(arr)))
        raise PhysicsRangeError(f"{name} must be finite; element {bad} is {arr[bad]}")
    if extrapolate:
        return
    mag = np.abs(arr)
    bad = (mag < lo) | (mag > hi)
    if bad.any():
        raise PhysicsRangeError(
            f"{name} = {arr[bad][0]:g} deg is outside the validity range {lo:g}-{hi:g} deg "
            f"of {what}; pass extrapolate=True to evaluate it anyway"
        )


def cie_gsf(
    theta_deg: Float[ArrayLike, "*shape"],
    age: Float[ArrayLike, "*shape"] = 25.0,
    pigmentation: Float[ArrayLike, "*shape"] = 0.5,
    *,
    extrapolate: bool = False,
) -> Float[Array, "*shape"]:
    """The CIE general disability glare equation: the human eye's glare spread function.

    With ``x = theta / 0.1°``, ``a4 = (A / 70)^4`` and ``p`` the pigmentation factor,

        L_eq / E_gl = (1 - 0.08 a4) [9.2e6 / (1 + (theta / 0.0046)²)^1.5
                                     + 1.5e5 / (1 + (theta / 0.045)²)^1.5]
                    + (1 + 1.6 a4) { 400 / (1 + x²) + 3e-8 theta²
                                     + p [1300 / (1 + x²)^1.5 + 0.8 / (1 + x²)^0.5] }
                    + 2.5e-3 p

    in sr⁻¹ with ``theta`` in degrees. This is the form of CIE 135/1-1999 (Vos &
    van den Berg) as kept in CIE 180:2010; the issue's transcription agrees with it
    term by term, as far as we can check without the standard at hand. Checks
    that the constants hang together: the two "optical" terms integrate over the
    plane to 0.37 + 0.58 ≈ 0.95 of the light (e.g. ``9.2e6 · 2π (0.0046°)² ·
    (π/180)² ≈ 0.373``), as a PSF normalised to about one should; and for ages
    25-80 and p 0-1.2 it stays within a factor 1.4 of the CIE's simpler
    "complete" equation ``10/theta³ + (5/theta² + 0.1 p/theta)[1 + (A/62.5)^4]
    + 0.0025 p`` at 0.1-100°. The small ``3e-8 theta²`` term (a slight upturn
    towards 100°) is part of the published equation, not a typo.

    With age, the first bracket (the steep core inside ~0.3°) is weighted down
    slightly and the second (the broad straylight) up steeply, so the function
    rises with age from ~0.2° out and falls slightly near 0.1°. The pigmentation
    terms stand for light entering through the eye wall (the translucent iris
    and sclera of light eyes); they matter mostly beyond ~10°.

    **Arguments:**

    - `theta_deg`: glare angle in degrees; the equation is stated for 0.1-100°.
    - `age`: age A in years, in 0-100 (default 25).
    - `pigmentation`: pigmentation factor p in 0-1.2: 0 very dark eyes, 0.5
      brown-eyed Caucasians (default), 1.0 blue-green-eyed Caucasians, 1.2 very
      light eyes.
    - `extrapolate`: evaluate outside 0.1-100° instead of raising (the formula is
      smooth and even in `theta`, but not validated there; at 0 it is finite).

    All three broadcast together. Differentiable in all three; `jit`/`vmap`-able.

    **Returns:** ``L_eq / E_gl`` in sr⁻¹ (same as (cd/m²)/lx).

    **Raises:** `PhysicsRangeError` (concrete inputs only) for a non-finite angle,
    an angle outside 0.1-100° without `extrapolate`, an age outside 0-100 or a
    pigmentation outside 0-1.2; the message names the value.

    **References:** CIE 135/1-1999 *Disability glare* (J. J. Vos, T. J. T. P. van den
    Berg); CIE 180:2010 *Disability glare*; J. J. Vos (2003), Clin. Exp. Optom. 86(6).

    **Example:**

    ```python
    cie_gsf(1.0)                       # 19.3 sr^-1 for a 25-year-old, brown eyes
    cie_gsf([0.1, 1, 10], age=70, pigmentation=1.0)
    ```
    """
    _check_angles("theta_deg", theta_deg, *CIE_GSF_RANGE_DEG, "the CIE glare equation", extrapolate)
    _check_interval("age", age, *AGE_RANGE_YEARS, "years")
    _check_interval(
        "pigmentation",
        pigmentation,
        *PIGMENTATION_RANGE,
        "",
        " (0 very dark eyes, 0.5 brown, 1.0 blue-green, 1.2 very light)",
    )
    return _cie_gsf(as_float(theta_deg), as_float(age), as_float(pigmentation))


# Jitted so that eager callers compile one program rather than each operation.
@jax.jit
def _cie_gsf(theta: Array, age: Array, p: Array) -> Array:
    a4 = (age / 70.0) ** 4
    t2 = theta * theta
    x2 = t2 / 0.1**2
    optics = 9.2e6 / (1.0 + t2 / 0.0046**2) ** 1.5 + 1.5e5 / (1.0 + t2 / 0.045**2) ** 1.5
    scatter = 400.0 / (1.0 + x2) + 3e-8 * t2
    pigment = 1300.0 / (1.0 + x2) ** 1.5 + 0.8 / jnp.sqrt(1.0 + x2)
    return (1.0 - 0.08 * a4) * optics + (1.0 + 1.6 * a4) * (scatter + p * pigment) + 2.5e-3 * p


def stiles_holladay(
    theta_deg: Float[ArrayLike, "*shape"],
    age: Float[ArrayLike, "*shape"] | None = None,
    *,
    extrapolate: bool = False,
) -> Float[Array, "*shape"]:
    """The Stiles–Holladay disability glare law, optionally age-adjusted (CIE).

    ``L_eq / E_gl = 10 / theta²`` (sr⁻¹, `theta` in degrees), the classical law of
    Holladay (1926) and Stiles (1929); with an `age` A, the CIE's age-adjusted
    form ``10 [1 + (A / 62.5)^4] / theta²``, whose factor is 2 at 62.5 years. Both
    are stated for 1-30°.

    **Arguments:**

    - `theta_deg`: glare angle in degrees (1-30 unless `extrapolate`).
    - `age`: age in years (0-100), or `None` for the plain law.
    - `extrapolate`: evaluate outside 1-30° instead of raising (it diverges at 0).

    **Returns:** ``L_eq / E_gl`` in sr⁻¹.

    **Raises:** `PhysicsRangeError` (concrete inputs) for an angle outside 1-30°
    without `extrapolate`, a zero or non-finite angle, or an age outside 0-100.

    **References:** CIE 135/1-1999; W. S. Stiles (1929), Proc. R. Soc. B 105;
    L. L. Holladay (1926), J. Opt. Soc. Am. 12.

    **Example:**

    ```python
    stiles_holladay(10.0)             # 0.1 sr^-1
    stiles_holladay(10.0, age=62.5)   # 0.2 sr^-1
    ```
    """
    _check_angles(
        "theta_deg",
        theta_deg,
        *STILES_HOLLADAY_RANGE_DEG,
        "the Stiles-Holladay law",
        extrapolate,
    )
    if is_concrete(theta_deg) and np.any(np.asarray(theta_deg, dtype=float) == 0):
        raise PhysicsRangeError("theta_deg = 0: the Stiles-Holladay law diverges at 0 deg")
    theta = as_float(theta_deg)
    value = 10.0 / (theta * theta)
    if age is None:
        return value
    _check_interval("age", age, *AGE_RANGE_YEARS, "years")
    return value * (1.0 + (as_float(age) / 62.5) ** 4)


def spencer_1995_psf(
    theta_deg: Float[ArrayLike, "*shape"],
    weights: tuple[float, float, float] = SPENCER_PHOTOPIC_WEIGHTS,
) -> Float[Array, "*shape"]:
    """The photopic point-spread function of the eye of Spencer et al. (1995).

    A weighted sum of three radial terms, `theta` in degrees, values in sr⁻¹:

        f0 = 2.61e6 exp(-(theta / 0.02)²)        (core)
        f1 = 20.91 / (theta + 0.02)³             (near wings)
        f2 = 72.37 / (theta + 0.02)²             (far wings)
        P  = 0.384 f0 + 0.478 f1 + 0.138 f2      (photopic)

    What we are sure of: `f0` and `f1` each integrate to 1 over the plane when
    the solid angle is in steradians (``2.61e6 · π (0.02)² (π/180)² = 0.9994`` and
    ``20.91 · π / 0.02 · (π/180)² = 1.0004``), which fixes their constants and
    shows the PSF is in sr⁻¹ with `theta` in degrees; and the photopic weights sum
    to 1. Recalled from the paper, not re-derivable: the `f2` constant 72.37 (its
    integral diverges logarithmically; it holds unit energy out to ~74°) and the
    weights 0.384 / 0.478 / 0.138. The paper's mesopic and scotopic PSFs add a
    wavelength-dependent lenticular-halo term `f3`, which is not implemented.

    **Arguments:**

    - `theta_deg`: angle from the point source in degrees (any value; the PSF is
      even in `theta`).
    - `weights`: weights of ``(f0, f1, f2)``; the default is the photopic PSF.

    **Returns:** the PSF in sr⁻¹.

    **Reference:** G. Spencer, P. Shirley, K. Zimmerman, D. P. Greenberg,
    "Physically-based glare effects for digital images", Proc. SIGGRAPH 1995,
    pp. 325-334.

    **Example:**

    ```python
    spencer_1995_psf(jnp.linspace(0.0, 10.0, 101))
    spencer_1995_psf(0.5, weights=(1.0, 0.0, 0.0))   # the core alone
    ```
    """
    if len(weights) != 3:
        raise ValueError(f"weights must hold 3 numbers (f0, f1, f2), got {weights!r}")
    theta = jnp.abs(as_float(theta_deg))
    w0, w1, w2 = weights
    f0 = 2.61e6 * jnp.exp(-((theta / 0.02) ** 2))
    shifted = theta + 0.02
    f1 = 20.91 / shifted**3
    f2 = 72.37 / shifted**2
    return w0 * f0 + w1 * f1 + w2 * f2
