"""Golden regression (`invglare regress`): every model and mode, recomputed and compared
with stored reference PSFs. An application on top of the library, in five parts:

- `invglare.regress.cases`: the registry of cases (small model configs) and their
  tolerances, with how the tolerances were calibrated;
- `invglare.regress.compare`: the five metrics of a recomputed PSF against its golden;
- `invglare.regress.goldens`: the stored EXR files, their headers, and updating them
  with a recorded reason (``CHANGES.md``);
- `invglare.regress.run`: computing the cases and comparing them, one result each;
- `invglare.regress.report`: ``regression.md`` and a difference image per case.

**Example:**

```python
from invglare.regress import run_suite, write_report

results = run_suite(golden_dir="tests/golden")
failed = [r.case.name for r in results if not r.passed]
write_report(results, "runs")
```
"""

from invglare.regress.cases import CASES as CASES
from invglare.regress.cases import DEFAULT_TOLERANCE as DEFAULT_TOLERANCE
from invglare.regress.cases import FRESNEL_TOLERANCE as FRESNEL_TOLERANCE
from invglare.regress.cases import Case as Case
from invglare.regress.cases import Tolerance as Tolerance
from invglare.regress.cases import select_cases as select_cases
from invglare.regress.compare import Metrics as Metrics
from invglare.regress.compare import compare_psfs as compare_psfs
from invglare.regress.compare import log_scaled as log_scaled
from invglare.regress.goldens import CHANGES_FILE as CHANGES_FILE
from invglare.regress.goldens import golden_path as golden_path
from invglare.regress.goldens import update_goldens as update_goldens
from invglare.regress.goldens import write_golden as write_golden
from invglare.regress.report import write_report as write_report
from invglare.regress.run import CaseResult as CaseResult
from invglare.regress.run import compute_case as compute_case
from invglare.regress.run import run_suite as run_suite
