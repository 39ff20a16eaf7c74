"""Differentiable rasterisation of apertures: soft primitives, composition and configs."""

from invglare.aperture.compose import Aperture as Aperture
from invglare.aperture.compose import occlude as occlude
from invglare.aperture.compose import union as union
from invglare.aperture.coverage import curved_edge_coverage as curved_edge_coverage
from invglare.aperture.coverage import edge_coverage as edge_coverage
from invglare.aperture.coverage import strip_coverage as strip_coverage
from invglare.aperture.primitives import ROLES as ROLES
from invglare.aperture.primitives import AbstractShape as AbstractShape
from invglare.aperture.primitives import Capsule as Capsule
from invglare.aperture.primitives import Disk as Disk
from invglare.aperture.primitives import Ellipse as Ellipse
from invglare.aperture.primitives import ImageMask as ImageMask
from invglare.aperture.primitives import RegularPolygon as RegularPolygon
from invglare.aperture.registry import SHAPE_KINDS as SHAPE_KINDS
from invglare.aperture.registry import shape_from_config as shape_from_config
from invglare.aperture.registry import shape_to_config as shape_to_config
