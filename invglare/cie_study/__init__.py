"""The CIE fitting study: the eye model's radial glare spread function fitted to the CIE's
(or to another reference, a PSF or GSF file). An application on top of the library:

- `invglare.cie_study.setup`: the fitted eye (pupil, light, particle populations) and its
  free parameters;
- `invglare.cie_study.annuli`: the radial GSF in logarithmic annuli, of the model and of a
  reference, on the same pixel centres;
- `invglare.cie_study.fit`: the fit (Levenberg–Marquardt in log units), its reasoning and
  its limits;
- `invglare.cie_study.report`: ``reports/cie/`` and the report folder of one fit;
- `invglare.cie_study.config`: the reader of fit configs with a ``[reference]`` table
  (``invglare fit fits/cie_A50_p1.toml``).

**Example:**

```python
from invglare.cie_study import CieFitSetup, fit_cie, write_cie_report

result = fit_cie(25.0, 0.5, CieFitSetup())   # minutes: compiles the eye, then fits
print(result.summary())                      # parameters, residual in log10 units
write_cie_report([result], "runs")           # runs/cie/cie.md and figures
```
"""

from invglare.cie_study.annuli import RadialBins as RadialBins
from invglare.cie_study.annuli import cie_target as cie_target
from invglare.cie_study.annuli import model_gsf as model_gsf
from invglare.cie_study.annuli import photopic_psf as photopic_psf
from invglare.cie_study.config import ReferenceFit as ReferenceFit
from invglare.cie_study.config import is_reference_fit as is_reference_fit
from invglare.cie_study.config import load_reference_fit as load_reference_fit
from invglare.cie_study.fit import CieFitResult as CieFitResult
from invglare.cie_study.fit import fit_cie as fit_cie
from invglare.cie_study.fit import fit_radial_gsf as fit_radial_gsf
from invglare.cie_study.fit import parse_cie_spec as parse_cie_spec
from invglare.cie_study.report import write_cie_report as write_cie_report
from invglare.cie_study.report import write_gsf_report as write_gsf_report
from invglare.cie_study.setup import CieFitSetup as CieFitSetup
from invglare.cie_study.setup import Population as Population
from invglare.cie_study.setup import build_fit_model as build_fit_model
