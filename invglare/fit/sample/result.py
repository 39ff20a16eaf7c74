"""What a chain holds, in physical units, and the progress reports of a run."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from invglare.fit.sample.posterior import SAMPLING_SPACE


class SampleProgress(NamedTuple):
    """One progress report, after each completed (and stored) step."""

    iteration: int
    max_steps: int
    acceptance: float
    tau_max: float


@dataclasses.dataclass
class SampleResult:
    """A chain with its diagnostics, in physical units.

    **Attributes:**

    - `paths`, `nuisance`: the parameters (order of the last axis) and which are nuisance.
    - `chain`: ``(steps, walkers, p)`` physical values; `latent`: the same in
      latent space (what emcee moved); `log_prob`: ``(steps, walkers)``.
    - `acceptance`: per-walker acceptance fraction.
    - `tau`: ``{path: integrated autocorrelation time}`` in steps (of the latent
      chain; NaN for a chain too short to estimate it at all).
    - `burn_in`, `thin`: steps discarded and kept-every used by :meth:`samples`
      (``2 max tau`` and ``min tau / 2``).
    - `converged`: longer than ``tau_factor`` τ for every parameter.
    - `warnings`: problems a user can act on, in words.
    - `moves`: ``[(name, weight)]`` of the last run; `runs`: every run (start
      step, moves, batch size, timing) recorded in the file.
    - `truth`, `fit_values`, `fit_stderr`: from the fit result, where known.
    - `timing`: seconds per step, per walker evaluation, compile time.
    - `path`: the HDF5 file.
    """

    paths: list[str]
    nuisance: list[str]
    chain: np.ndarray
    latent: np.ndarray
    log_prob: np.ndarray
    acceptance: np.ndarray
    tau: dict[str, float]
    burn_in: int
    thin: int
    converged: bool
    warnings: list[str]
    moves: list[tuple[str, float]]
    tau_factor: float = 50.0
    runs: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    truth: dict[str, float] | None = None
    fit_values: dict[str, float] = dataclasses.field(default_factory=dict)
    fit_stderr: dict[str, float] = dataclasses.field(default_factory=dict)
    timing: dict[str, float] = dataclasses.field(default_factory=dict)
    sampling_space: str = SAMPLING_SPACE
    likelihood: str = "pixels"
    path: Path | None = None

    @property
    def n_steps(self) -> int:
        return int(self.chain.shape[0])

    @property
    def n_walkers(self) -> int:
        return int(self.chain.shape[1])

    def samples(
        self, discard: int | None = None, thin: int | None = None, flat: bool = True
    ) -> np.ndarray:
        """Physical samples after burn-in: ``(n, p)`` if `flat`, else ``(steps, walkers, p)``."""
        d = self.burn_in if discard is None else int(discard)
        t = self.thin if thin is None else int(thin)
        out = self.chain[d::t]
        return out.reshape(-1, out.shape[-1]) if flat else out

    def effective_samples(self) -> dict[str, float]:
        """``walkers * (steps - burn_in) / tau`` per parameter."""
        n = self.n_walkers * max(self.n_steps - self.burn_in, 0)
        return {p: (n / t if t > 0 else math.nan) for p, t in self.tau.items()}

    def percentiles(self) -> dict[str, dict[str, float]]:
        """Per parameter: median, 16/84 and 2.5/97.5 percentiles, mean and std."""
        s = self.samples()
        out = {}
        for i, p in enumerate(self.paths):
            q = np.percentile(s[:, i], [2.5, 16, 50, 84, 97.5])
            out[p] = {
                "median": float(q[2]),
                "p16": float(q[1]),
                "p84": float(q[3]),
                "p2_5": float(q[0]),
                "p97_5": float(q[4]),
                "mean": float(s[:, i].mean()),
                "std": float(s[:, i].std(ddof=1)) if len(s) > 1 else math.nan,
            }
        return out

    def correlation(self) -> np.ndarray:
        """``(p, p)`` correlation matrix of the physical samples."""
        return np.corrcoef(self.samples(), rowvar=False).reshape(len(self.paths), -1)

    def summary(self) -> str:
        """A plain-text table: median with 16/84 percentiles, τ, truth where known."""
        pc = self.percentiles()
        head = (
            f"{self.n_steps} steps x {self.n_walkers} walkers, burn-in {self.burn_in}, "
            f"thin {self.thin}, acceptance {self.acceptance.mean():.3f}, "
            f"{'converged' if self.converged else 'NOT converged'}"
        )
        lines = [head]
        for p in self.paths:
            v = pc[p]
            line = (
                f"  {p}: {v['median']:.6g} +{v['p84'] - v['median']:.3g} "
                f"-{v['median'] - v['p16']:.3g}  (tau {self.tau[p]:.1f})"
            )
            if self.truth and p in self.truth:
                line += f"  truth {self.truth[p]:.6g}"
            lines.append(line)
        lines += [f"  warning: {w}" for w in self.warnings]
        return "\n".join(lines)
