"""Posterior sampling of a fit with emcee: log-probability, walkers, checkpoints, convergence.

The package face: import from here (``from invglare.fit.sample import sample``). The
modules behind it, in the order a run uses them:

| module        | what it holds                                                              |
|---------------|----------------------------------------------------------------------------|
| `posterior`   | :class:`LogPosterior` (likelihood + prior + latent Jacobian), the prior checks |
| `batching`    | :class:`BatchedLogProb` (emcee's vectorised call), :func:`tune_batch_size`   |
| `moves`       | :data:`MOVES` and :func:`parse_moves`                                        |
| `walkers`     | :func:`initial_walkers`: the starting ball around the fit                    |
| `signals`     | Ctrl-C / SIGTERM held while a step is written                                |
| `chain`       | the HDF5 chain file and its metadata; :func:`load_chain`                     |
| `diagnostics` | autocorrelation times, burn-in, thinning, warnings (:func:`diagnose`)        |
| `result`      | :class:`SampleResult`, :class:`SampleProgress`                               |
| `run`         | :func:`sample`: the checkpointed run (its docstring tells the whole story)   |

**Example:**

```python
from invglare.fit import fit
from invglare.fit.sample import sample

res = fit(space, forward, photo)
post = sample(space, forward, photo, res, "chain.h5", n_walkers=32, max_steps=5000)
print(post.summary())
```
"""

from invglare.fit.sample.batching import BatchedLogProb as BatchedLogProb
from invglare.fit.sample.batching import tune_batch_size as tune_batch_size
from invglare.fit.sample.chain import CHAIN_GROUP as CHAIN_GROUP
from invglare.fit.sample.chain import FORMAT as FORMAT
from invglare.fit.sample.chain import META_GROUP as META_GROUP
from invglare.fit.sample.chain import VERSION as VERSION
from invglare.fit.sample.chain import load_chain as load_chain
from invglare.fit.sample.diagnostics import diagnose as diagnose
from invglare.fit.sample.moves import MOVES as MOVES
from invglare.fit.sample.moves import parse_moves as parse_moves
from invglare.fit.sample.posterior import LIKELIHOODS as LIKELIHOODS
from invglare.fit.sample.posterior import MIN_PRIOR_MASS as MIN_PRIOR_MASS
from invglare.fit.sample.posterior import SAMPLING_SPACE as SAMPLING_SPACE
from invglare.fit.sample.posterior import LogPosterior as LogPosterior
from invglare.fit.sample.posterior import check_priors as check_priors
from invglare.fit.sample.posterior import fingerprint as fingerprint
from invglare.fit.sample.posterior import make_log_posterior as make_log_posterior
from invglare.fit.sample.posterior import prior_mass as prior_mass
from invglare.fit.sample.result import SampleProgress as SampleProgress
from invglare.fit.sample.result import SampleResult as SampleResult
from invglare.fit.sample.run import sample as sample
from invglare.fit.sample.walkers import initial_walkers as initial_walkers

__all__ = [
    "MOVES",
    "BatchedLogProb",
    "LogPosterior",
    "SampleProgress",
    "SampleResult",
    "check_priors",
    "diagnose",
    "fingerprint",
    "initial_walkers",
    "load_chain",
    "make_log_posterior",
    "parse_moves",
    "sample",
    "tune_batch_size",
]
