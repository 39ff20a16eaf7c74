"""Reference PSFs: the CIE glare spread function, closed-form diffraction, profiles.

- `invglare.reference.cie`: the CIE general disability glare equation, the
  (age-adjusted) Stiles–Holladay law and the photopic PSF of Spencer et al. 1995,
  all in sr⁻¹ against the angle in degrees.
- `invglare.reference.closed_forms`: unit-energy far fields in sr⁻¹ of a disk
  (Airy), a rectangle (sinc²) and any polygon (edge sum), and the Fresnel
  diffraction of a square — cross-checks for the numerical propagators.
- `invglare.reference.profiles`: radial profiles, encircled energy, conversion
  between 1-D GSFs (sr⁻¹) and 2-D PSFs (energy per pixel), reference files.
"""

from invglare.reference.cie import AGE_RANGE_YEARS as AGE_RANGE_YEARS
from invglare.reference.cie import CIE_GSF_RANGE_DEG as CIE_GSF_RANGE_DEG
from invglare.reference.cie import PIGMENTATION_RANGE as PIGMENTATION_RANGE
from invglare.reference.cie import SPENCER_PHOTOPIC_WEIGHTS as SPENCER_PHOTOPIC_WEIGHTS
from invglare.reference.cie import STILES_HOLLADAY_RANGE_DEG as STILES_HOLLADAY_RANGE_DEG
from invglare.reference.cie import cie_gsf as cie_gsf
from invglare.reference.cie import spencer_1995_psf as spencer_1995_psf
from invglare.reference.cie import stiles_holladay as stiles_holladay
from invglare.reference.closed_forms import airy_encircled_energy as airy_encircled_energy
from invglare.reference.closed_forms import airy_pixel_psf as airy_pixel_psf
from invglare.reference.closed_forms import airy_psf as airy_psf
from invglare.reference.closed_forms import bessel_j1 as bessel_j1
from invglare.reference.closed_forms import fresnel_square_intensity as fresnel_square_intensity
from invglare.reference.closed_forms import jinc as jinc
from invglare.reference.closed_forms import polygon_area_mm2 as polygon_area_mm2
from invglare.reference.closed_forms import polygon_far_field as polygon_far_field
from invglare.reference.closed_forms import polygon_fourier_transform as polygon_fourier_transform
from invglare.reference.closed_forms import rect_psf as rect_psf
from invglare.reference.closed_forms import regular_polygon_vertices as regular_polygon_vertices
from invglare.reference.profiles import NORMALISATIONS as NORMALISATIONS
from invglare.reference.profiles import TABLE_SUFFIXES as TABLE_SUFFIXES
from invglare.reference.profiles import RadialTable as RadialTable
from invglare.reference.profiles import ReferenceImage as ReferenceImage
from invglare.reference.profiles import encircled_energy as encircled_energy
from invglare.reference.profiles import gsf_to_psf as gsf_to_psf
from invglare.reference.profiles import load_reference_psf as load_reference_psf
from invglare.reference.profiles import psf_to_gsf as psf_to_gsf
from invglare.reference.profiles import radial_profile as radial_profile
