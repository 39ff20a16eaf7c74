"""The temporal eye's frames by progressive quads (Scandolo et al., sec. 4.3, on Ritschel et al.).

:meth:`~invglare.models.temporal.TemporalGlare.psf_sequence` transforms every frame's
aperture whole (one FFT of the aperture times the sampled Fresnel term, eq. 3). A blink,
the hippus and moving particles change only part of the aperture from one frame to the
next: :func:`progressive_psf_sequence` transforms the first frame's quads and then only the
quads of each frame's difference (:class:`~invglare.optics.quad.progressive.
ProgressiveQuads`), in the near field of the model's Fresnel term by closed-form Fresnel
integrals (no chirp to sample; ``fresnel = "none"``: the far field), on the model's own
output grid (at the retina's 17 mm the float32 phases are refused with the reason: enable
float64), and makes the spectral
image by the model's scaled copies. The frames are those of the model's dynamics
(:meth:`~invglare.models.temporal.TemporalGlare.aperture_sequence`, one compiled scan).

It works on concrete values, frame after frame (a rendering loop, not a fit).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from invglare.models.temporal import TemporalGlare
from invglare.optics.fraunhofer import transmitted_power
from invglare.optics.quad.progressive import FrameStats, ProgressiveQuads
from invglare.optics.spectral import scaled_copies, xyz_to_rgb


def progressive_psf_sequence(
    model: TemporalGlare,
    n_frames: int,
    luminance_cd_m2: Float[ArrayLike, "*n"] | None = None,
    *,
    refresh_every: int = 0,
) -> tuple[np.ndarray, list[FrameStats]]:
    """PSFs of `n_frames` frames of the temporal eye by progressive quads.

    **Arguments:** as :meth:`~invglare.models.temporal.TemporalGlare.psf_sequence`;
    `refresh_every` re-evaluates a frame from scratch every so many frames (0: only the
    first).

    **Returns:** the PSFs, ``(n, npix, npix[, 3])`` like :meth:`psf_sequence` (per unit power
    through the aperture, or scaled by the transmitted power with ``brightness =
    "transmitted"``), and each frame's :class:`~invglare.optics.quad.progressive.FrameStats`.
    """
    prop, spec = model.propagator, model.spectrum
    run = eqx.filter_jit(lambda m, lum: m.aperture_sequence(n_frames, lum))
    _, apertures = run(model, luminance_cd_m2)
    # The distance of the model's Fresnel term E: the retina (on the model's image-plane
    # grid), the effective distance (at the FFT's native scale), or none (far field).
    distance = {
        "retina": float(prop.focal_length_mm),
        "effective": model.fresnel_distance_mm,
        "none": None,
    }[model.fresnel]
    progressive = ProgressiveQuads(
        prop.grid,
        prop.output,
        spec.reference_wavelength_nm,
        None if distance is None else float(distance),
        refresh_every=refresh_every,
    )
    if model.is_spectral:
        factors = jnp.asarray(spec.wavelengths_nm) / spec.reference_wavelength_nm
        weights = xyz_to_rgb(jnp.asarray(spec.weights_xyz), spec.colourspace)
        spectral = jax.jit(lambda mono: jnp.moveaxis(scaled_copies(mono, factors, weights), 0, -1))
    frames = []
    for aperture in np.asarray(apertures):
        mono = progressive.psf(aperture)
        if model.brightness == "transmitted":
            mono = mono * float(transmitted_power(jnp.asarray(aperture), prop.grid.pitch_mm))
        frames.append(np.asarray(spectral(jnp.asarray(mono))) if model.is_spectral else mono)
    return np.stack(frames), progressive.stats
