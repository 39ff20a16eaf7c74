"""Inverse modelling: parameter spaces, the observation model, views, fitting and results.

```python
from invglare.fit import Forward, Observation, Parameter, ParameterSpace, fit

space = ParameterSpace(
    [Parameter("model.aperture.shapes[0].diameter_mm", 2.0, 5.0, init=3.5)],
    nuisance=[Parameter("obs.flux", 0.0, float("inf"), init=1e6)],
)
result = fit(space, Forward(model, Observation.from_target(photo)), photo, {"pixels": 1.0})
```
"""

from invglare.fit.deviance import deviance_residuals as deviance_residuals
from invglare.fit.deviance import likelihood_peak as likelihood_peak
from invglare.fit.observation import Forward as Forward
from invglare.fit.observation import Observation as Observation
from invglare.fit.observation import check_target as check_target
from invglare.fit.observation import disk_kernel as disk_kernel
from invglare.fit.observation import fourier_shift as fourier_shift
from invglare.fit.observation import rotate_image as rotate_image
from invglare.fit.observation import soft_clip as soft_clip
from invglare.fit.params import Parameter as Parameter
from invglare.fit.params import ParameterSpace as ParameterSpace
from invglare.fit.params import Prior as Prior
from invglare.fit.params import parse_path as parse_path
from invglare.fit.params import resolve_path as resolve_path
from invglare.fit.params import valid_paths as valid_paths
from invglare.fit.photos import PhotoFits as PhotoFits
from invglare.fit.photos import fit_photos as fit_photos
from invglare.fit.result import FitResult as FitResult
from invglare.fit.solve import FitProgress as FitProgress
from invglare.fit.solve import fit as fit
from invglare.fit.views import VIEWS as VIEWS
from invglare.fit.views import AbstractView as AbstractView
from invglare.fit.views import AngularView as AngularView
from invglare.fit.views import HaloView as HaloView
from invglare.fit.views import PixelView as PixelView
from invglare.fit.views import RadialView as RadialView
from invglare.fit.views import ResidualFn as ResidualFn
from invglare.fit.views import ViewContext as ViewContext
from invglare.fit.views import angular_bin_angles_deg as angular_bin_angles_deg
from invglare.fit.views import angular_energy as angular_energy
from invglare.fit.views import box_downsample as box_downsample
from invglare.fit.views import generalised_anscombe as generalised_anscombe
from invglare.fit.views import halo_ring_radius as halo_ring_radius
from invglare.fit.views import make_residual_fn as make_residual_fn
from invglare.fit.views import pixel_residuals as pixel_residuals
from invglare.fit.views import radial_bin_radii as radial_bin_radii
from invglare.fit.views import radial_profile as radial_profile
