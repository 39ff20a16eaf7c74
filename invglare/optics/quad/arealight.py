"""Area lights with per-sample occlusion (sec. 4.4 and 6.1 of Scandolo et al.).

An area light is many point samples; each sees the aperture through the scene from its own
position, so each has its own visible aperture (the aperture times what an occluder in
front of it leaves open) and its own PSF. The glare image is their sum, each PSF centred on
its sample's direction and scaled by the light that sample gets through.

Here the occluder is a raster in a plane a distance `occluder_distance_mm` in front of the
aperture: seen from a sample at angle ``theta`` its shadow is displaced by ``-d
tan(theta)`` (the parallax of eq. 3 of Kakimoto et al.), shifted with linear interpolation.
Samples sit on the output grid's pixels (integer offsets from the light's centre), so that
each PSF lands on the image without resampling; visiting them in a serpentine order keeps
consecutive visible apertures close, and the progressive update (:mod:`.progressive`)
evaluates only what changes from one sample to the next.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from invglare._core.checks import check_range
from invglare.errors import InputDataError
from invglare.optics.quad.progressive import ProgressiveQuads


def serpentine(offsets_px: np.ndarray) -> np.ndarray:
    """An order of integer offsets ``(dy, dx)`` row by row, every other row reversed."""
    offsets = np.asarray(offsets_px)
    key = np.where(offsets[:, 0] % 2 == 0, offsets[:, 1], -offsets[:, 1])
    return np.lexsort((key, offsets[:, 0]))


def visible_aperture(
    aperture: np.ndarray, occluder: np.ndarray, shift_px: tuple[float, float]
) -> np.ndarray:
    """The aperture times the transmission ``1 - occluder`` shifted by ``(dy, dx)`` pixels."""
    moved = ndimage.shift(occluder, shift_px, order=1, mode="constant", cval=0.0)
    return aperture * (1.0 - np.clip(moved, 0.0, 1.0))


def area_light_image(
    progressive: ProgressiveQuads,
    aperture: np.ndarray,
    offsets_px: np.ndarray,
    radiance: np.ndarray,
    occluder: np.ndarray | None = None,
    occluder_distance_mm: float = 0.0,
) -> np.ndarray:
    """The glare image of an area light whose samples each see their own aperture.

    **Arguments:**

    - `progressive`: a :class:`~invglare.optics.quad.progressive.ProgressiveQuads` on the
      aperture's grid and the image's output grid (far or near field), fresh.
    - `aperture`: the aperture's raster (transmission) on that grid.
    - `offsets_px`: ``(S, 2)`` integer ``(dy, dx)`` output pixels of the samples from the
      image centre.
    - `radiance`: ``(S,)`` each sample's share of the light (>= 0).
    - `occluder`: the occluder's coverage raster on the aperture grid (None: no occluder).
    - `occluder_distance_mm`: its distance in front of the aperture (>= 0).

    **Returns:** the image on the output grid: per pixel, the light's power reaching it
    in units of the power a sample with radiance 1 sends through the unoccluded aperture.
    """
    offsets = np.asarray(offsets_px)
    radiance = np.asarray(radiance, dtype=np.float64)
    if offsets.ndim != 2 or offsets.shape[1] != 2 or not np.issubdtype(offsets.dtype, np.integer):
        raise InputDataError(
            f"offsets_px must be integer (S, 2) pixel offsets, got {offsets.shape}"
        )
    if radiance.shape != (offsets.shape[0],) or np.any(radiance < 0):
        raise InputDataError("radiance must hold one value >= 0 per sample")
    check_range("occluder_distance_mm", occluder_distance_mm, 0.0, unit="mm")
    n = progressive.output.npix
    # Powers through the aperture, its transmission sum |t| (each PSF is per unit of it).
    open_power = float(np.sum(np.abs(aperture)))
    if open_power <= 0:
        raise InputDataError("the aperture is empty: nothing is transmitted")
    scale = math.radians(float(progressive.output.pixel_scale_deg))
    pitch = float(progressive.grid.pitch_mm)
    image = np.zeros((n, n))
    for s in serpentine(offsets):
        dy, dx = (int(v) for v in offsets[s])
        if occluder is None:
            visible = aperture
        else:
            # The shadow moves against the sample's direction (parallax, -d tan(theta)).
            shift = tuple(-occluder_distance_mm * math.tan(v * scale) / pitch for v in (dy, dx))
            visible = visible_aperture(aperture, occluder, shift)
        power = float(np.sum(np.abs(visible)))
        if power <= 0:
            continue  # this sample sees nothing
        psf = progressive.psf(visible) * (radiance[s] * power / open_power)
        image += _shifted(psf, dy, dx)
    return image


def _shifted(image: np.ndarray, dy: int, dx: int) -> np.ndarray:
    """`image` moved by whole pixels, zero-filled (what leaves the field is dropped)."""
    out = np.zeros_like(image)
    n0, n1 = image.shape
    src_r = slice(max(0, -dy), min(n0, n0 - dy))
    dst_r = slice(max(0, dy), min(n0, n0 + dy))
    src_c = slice(max(0, -dx), min(n1, n1 - dx))
    dst_c = slice(max(0, dx), min(n1, n1 + dx))
    out[dst_r, dst_c] = image[src_r, src_c]
    return out
