"""Quad-based analytic Fourier transforms (Scandolo, Lee & Eisemann 2018) and exact polygons.

| module | what it does |
|---|---|
| `quadtree` | quads of a (soft) raster: bottom-up quadtree, 2:1 merges, negative quads |
| `plan` | distinct intervals, mirror symmetries, padded plans for frame loops |
| `transform` | closed-form quad transforms (exact sinc), parity split, matrix products |
| `farfield`, `nearfield` | Fraunhofer PSF; Fresnel PSF by Fresnel integrals (two passes) |
| `cull` | culling of negligible output tiles from a coarse pass with derivatives |
| `progressive` | animated apertures by difference quads; the paper's moving shadow |
| `spectral` | batch spectral scaling (eq. 14-16) |
| `arealight` | area lights whose samples see their own occluded aperture |
| `polygon`, `outline` | exact polygon / ellipse transforms; invglare's shapes as pieces |
| `options`, `prepare` | the methods' options; what propagators decide before a call |
| `apertures` | the paper's box, circle, heptagon and whirl |

The propagators (`method = "quad"`, `"polygon"`) are in :mod:`invglare.optics.propagator`.
"""

from invglare.optics.quad.arealight import area_light_image as area_light_image
from invglare.optics.quad.cull import cull_tiles as cull_tiles
from invglare.optics.quad.cull import culling_error as culling_error
from invglare.optics.quad.farfield import quad_far_field as quad_far_field
from invglare.optics.quad.nearfield import quad_near_field as quad_near_field
from invglare.optics.quad.options import PolygonOptions as PolygonOptions
from invglare.optics.quad.options import QuadOptions as QuadOptions
from invglare.optics.quad.plan import QuadPlan as QuadPlan
from invglare.optics.quad.plan import detect_mirrors as detect_mirrors
from invglare.optics.quad.plan import make_plan as make_plan
from invglare.optics.quad.polygon import ellipse_transform as ellipse_transform
from invglare.optics.quad.polygon import polygon_transform as polygon_transform
from invglare.optics.quad.progressive import ProgressiveQuads as ProgressiveQuads
from invglare.optics.quad.progressive import moving_shadow as moving_shadow
from invglare.optics.quad.quadtree import QuadLayout as QuadLayout
from invglare.optics.quad.quadtree import build_quadtree as build_quadtree
from invglare.optics.quad.spectral import BatchPlan as BatchPlan
from invglare.optics.quad.spectral import batch_scaled_copies as batch_scaled_copies
from invglare.optics.quad.transform import sinc as sinc
