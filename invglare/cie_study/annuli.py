"""Radial GSFs in logarithmic annuli: the statistic the CIE study fits.

The model's GSF (sr⁻¹: the PSF, energy per pixel, over the pixel solid angle) and a
reference's are both averaged over the *same pixel centres* of each annulus: both are
point samples of a sr⁻¹ function, so the comparison is exact in its geometry.

**Example:**

```python
bins = RadialBins.build(108, 0.02, 0.1, 0.99, 20)   # npix, deg/px, range (deg), annuli
target = cie_target(50.0, 1.0, bins)                 # the CIE GSF per annulus (sr^-1)
```
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import numpy as np
from jaxtyping import Array, Float

from invglare.errors import PhysicsRangeError

__all__ = ["RadialBins", "annulus_mean", "cie_target", "model_gsf", "photopic_psf"]


@dataclasses.dataclass(frozen=True, eq=False)
class RadialBins:
    """Logarithmic annuli on the output grid: which pixel goes where (static, numpy).

    **Fields:** `index` (per pixel, the annulus or `n_bins` for none), `counts`
    (pixels per annulus), `theta_deg` (mean pixel-centre angle per annulus), `edges_deg`,
    `pixel_theta_deg` (every pixel centre's angle), `pixel_scale_deg`.
    """

    index: np.ndarray
    counts: np.ndarray
    theta_deg: np.ndarray
    edges_deg: np.ndarray
    pixel_theta_deg: np.ndarray
    pixel_scale_deg: float

    @classmethod
    def build(cls, npix: int, pixel_scale_deg: float, lo_deg: float, hi_deg: float, n: int):
        c = npix // 2
        yy, xx = np.mgrid[:npix, :npix] - c
        theta = np.hypot(xx, yy) * pixel_scale_deg
        edges = np.geomspace(lo_deg, hi_deg, n + 1)
        idx = np.searchsorted(edges, theta, side="right") - 1
        idx = np.where((theta >= lo_deg) & (theta < hi_deg), idx, n)
        counts = np.bincount(idx.ravel(), minlength=n + 1)[:n]
        if np.any(counts == 0):
            empty = int(np.argmax(counts == 0))
            raise PhysicsRangeError(
                f"annulus {empty} ({edges[empty]:.3g}-{edges[empty + 1]:.3g} deg) holds no "
                f"pixel centre at {pixel_scale_deg:g} deg/px; use fewer bins or finer pixels"
            )
        sums = np.bincount(idx.ravel(), weights=theta.ravel(), minlength=n + 1)[:n]
        return cls(idx.ravel(), counts, sums / counts, edges, theta, float(pixel_scale_deg))

    @property
    def n_bins(self) -> int:
        return int(self.counts.size)

    def mean(self, image) -> Any:
        """Mean of a ``(npix, npix)`` image per annulus (jax.numpy, differentiable)."""
        import jax.numpy as jnp

        flat = jnp.reshape(image, (-1,))
        sums = jnp.zeros(self.n_bins + 1, flat.dtype).at[self.index].add(flat)[: self.n_bins]
        return sums / jnp.asarray(self.counts, flat.dtype)


def photopic_psf(model) -> Float[Array, "npix npix"]:
    """The luminance (photopic, V(λ)-weighted) PSF of a Kakimoto model, unit energy.

    One field, propagated at each wavelength, summed with the Y weights of the model's
    spectrum (normalised to 1): the Y of its RGB PSF, without the RGB round trip.
    """
    import jax
    import jax.numpy as jnp

    field = model.field()
    lams = model.spectrum.wavelengths_nm
    psfs = jax.vmap(lambda lam: model.propagator(field, lam))(lams)
    wy = model.spectrum.weights_xyz[:, 1]
    return jnp.tensordot(wy / jnp.sum(wy), psfs, axes=1)


def model_gsf(model, bins: RadialBins) -> Float[Array, " n_bins"]:
    """The model's photopic GSF (sr⁻¹) per annulus: PSF over pixel solid angle, averaged."""
    omega = math.radians(bins.pixel_scale_deg) ** 2
    return bins.mean(photopic_psf(model)) / omega


def annulus_mean(gsf: Callable[[Any], Any], bins: RadialBins) -> np.ndarray:
    """A radial function (of angle in degrees) averaged over each annulus's pixel centres,
    the way :func:`model_gsf` averages the model: both are point samples of one function."""
    import jax

    with jax.enable_x64(True):
        inside = bins.index < bins.n_bins
        values = np.zeros(bins.index.size)
        values[inside] = np.asarray(gsf(bins.pixel_theta_deg.ravel()[inside]))
    sums = np.bincount(bins.index, weights=values, minlength=bins.n_bins + 1)[: bins.n_bins]
    return sums / bins.counts


def cie_target(age: float, pigmentation: float, bins: RadialBins) -> np.ndarray:
    """The CIE GSF (sr⁻¹) averaged over each annulus's pixel centres, like :func:`model_gsf`."""
    from invglare.reference.cie import cie_gsf

    # Validate age and pigmentation on scalars first: errors then name the value.
    cie_gsf(1.0, age, pigmentation)
    return annulus_mean(lambda t: cie_gsf(t, age, pigmentation), bins)
