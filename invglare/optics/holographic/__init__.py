"""The holographic layered eye of Novosad & Ziegler: point sources, thin layers, retina.

- :mod:`.sampling`: the grids (one output grid of directions, one aperture grid per
  colour) and how many depth layers a depth range needs;
- :mod:`.sources`: point sources from a frame and its depth buffer (view frustum,
  amplitudes, random phases, the FFT-bin layout);
- :mod:`.base_layer`: the field of the sources at the first plane (eq. 2.2 by brute force;
  the fast Fresnel path by depth layers);
- :mod:`.layers`: thin phase layers (curvature, lens, spectacles) and the band-limited
  angular-spectrum kernels between planes;
- :mod:`.tear_film`: the tear film as a (static or animated) height field;
- :mod:`.stack`: the whole stack, iterations against speckle and the speckle-free limit.
"""

from invglare.optics.holographic.base_layer import (
    fresnel_base_field,
    plane_wave_sum,
    spherical_wave_sum,
)
from invglare.optics.holographic.layers import (
    Spectacles,
    propagate_periodic,
    propagation_kernel,
    spectacle_phase,
    thin_lens_phase,
    vergence_chirp,
)
from invglare.optics.holographic.sampling import (
    HoloSampling,
    depth_layers_needed,
    vergence_step_per_mm,
)
from invglare.optics.holographic.sources import (
    DEPTH_ENCODINGS,
    PHASES,
    Frustum,
    bins_to_image,
    decode_depth,
    image_to_bins,
    layer_vergences,
    random_phasors,
    reproject,
)
from invglare.optics.holographic.stack import (
    ChannelStack,
    iterate_intensity,
    iteration_bytes,
    point_response,
    speckle_contrast,
    speckle_free,
    stack_field,
)
from invglare.optics.holographic.tear_film import TEAR_PATTERNS, TearFilm

__all__ = [
    "DEPTH_ENCODINGS",
    "PHASES",
    "TEAR_PATTERNS",
    "ChannelStack",
    "Frustum",
    "HoloSampling",
    "Spectacles",
    "TearFilm",
    "bins_to_image",
    "decode_depth",
    "depth_layers_needed",
    "fresnel_base_field",
    "image_to_bins",
    "iterate_intensity",
    "iteration_bytes",
    "layer_vergences",
    "plane_wave_sum",
    "point_response",
    "propagate_periodic",
    "propagation_kernel",
    "random_phasors",
    "reproject",
    "speckle_contrast",
    "speckle_free",
    "spectacle_phase",
    "spherical_wave_sum",
    "stack_field",
    "thin_lens_phase",
    "vergence_chirp",
    "vergence_step_per_mm",
]
