"""Soft shapes: analytic pixel coverage, primitives, their composition, stamps and tables.

- :mod:`~invglare.aperture.shapes.coverage`: exact coverage of a pixel by an edge;
- :mod:`~invglare.aperture.shapes.primitives`: disks, ellipses, polygons, capsules, images;
- :mod:`~invglare.aperture.shapes.compose`: open and blocking shapes made one aperture;
- :mod:`~invglare.aperture.shapes.stamps`: many small occluders on local windows;
- :mod:`~invglare.aperture.shapes.schema`: the config tables of shapes and their writer.
"""

from invglare.aperture.shapes.compose import Aperture as Aperture
from invglare.aperture.shapes.compose import occlude as occlude
from invglare.aperture.shapes.compose import union as union
from invglare.aperture.shapes.coverage import curved_edge_coverage as curved_edge_coverage
from invglare.aperture.shapes.coverage import edge_coverage as edge_coverage
from invglare.aperture.shapes.coverage import strip_coverage as strip_coverage
from invglare.aperture.shapes.primitives import ROLES as ROLES
from invglare.aperture.shapes.primitives import AbstractShape as AbstractShape
from invglare.aperture.shapes.primitives import Capsule as Capsule
from invglare.aperture.shapes.primitives import Disk as Disk
from invglare.aperture.shapes.primitives import Ellipse as Ellipse
from invglare.aperture.shapes.primitives import ImageMask as ImageMask
from invglare.aperture.shapes.primitives import RegularPolygon as RegularPolygon
from invglare.aperture.shapes.schema import SHAPE_KINDS as SHAPE_KINDS
from invglare.aperture.shapes.schema import shape_to_config as shape_to_config
