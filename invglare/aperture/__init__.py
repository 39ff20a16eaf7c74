"""Differentiable rasterisation of apertures: soft shapes, the eye and the camera.

- :mod:`invglare.aperture.shapes`: soft primitives, their composition, stamps, tables;
- :mod:`invglare.aperture.eye`: the eye (pupil, lids, lashes, particles, gratings);
- :mod:`invglare.aperture.camera`: the camera (diaphragm, cross-screen filter, dust).

The shapes are re-exported here. Configuration tables are written by this tier
(``shape_to_config``, ``eye_to_config``, ``camera_to_config``) and read by the config
tier (:mod:`invglare.config.shapes`, :mod:`invglare.config.eye`,
:mod:`invglare.config.camera`).
"""

from invglare.aperture.shapes import ROLES as ROLES
from invglare.aperture.shapes import SHAPE_KINDS as SHAPE_KINDS
from invglare.aperture.shapes import AbstractShape as AbstractShape
from invglare.aperture.shapes import Aperture as Aperture
from invglare.aperture.shapes import Capsule as Capsule
from invglare.aperture.shapes import Disk as Disk
from invglare.aperture.shapes import Ellipse as Ellipse
from invglare.aperture.shapes import ImageMask as ImageMask
from invglare.aperture.shapes import RegularPolygon as RegularPolygon
from invglare.aperture.shapes import curved_edge_coverage as curved_edge_coverage
from invglare.aperture.shapes import edge_coverage as edge_coverage
from invglare.aperture.shapes import occlude as occlude
from invglare.aperture.shapes import shape_to_config as shape_to_config
from invglare.aperture.shapes import strip_coverage as strip_coverage
from invglare.aperture.shapes import union as union
