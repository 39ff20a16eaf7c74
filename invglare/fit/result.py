"""The result of a fit: values with uncertainties, diagnostics, and a JSON file to keep them.

The JSON layout (``params.json`` of a fit report) is

```json
{
  "format": "invglare.fit", "version": 1,
  "parameters": {"model.aperture.shapes[0].diameter_mm":
                   {"value": 3.01, "stderr": 0.02, "truth": 3.0, "nuisance": false}},
  "covariance": {"paths": [...], "matrix": [[...]]},
  "loss": 4012.5, "reduced_chi2": 0.98, "n_residuals": 4096, "covariance_scale": 0.98,
  "converged": true, "message": "converged ...", "n_steps": 23, "best_start": 1,
  "timing_s": {"compile": 4.1, "solve": 0.8, "total": 5.3},
  "solver": "lm", "views": {"pixels": 1.0},
  "objective": "the Poisson–Gaussian likelihood of the pixels (deviance residuals, ...)",
  "flags": [{"kind": "truth_beyond_3se", "path": "obs.background", "z": -6.9,
             "message": "obs.background: the truth 20 is -6.9 standard errors from ..."}],
  "optimum_check": {"gain": 0.002, "decrement": 0.05, "steps": 1},
  "stages": [{"factor": 4, "n_steps": [...], "final_loss": [...], "converged": [...],
              "messages": [...], "loss_history": [[...], ...], "compile_s": 2.0, "solve_s": 0.3}],
  "starts": [{"path": value, ...}, ...]
}
```

``"flags"`` says when to distrust the result (:mod:`invglare.fit.trust`): each flag has
a ``"kind"`` — ``"not_at_optimum"`` (a few scoring steps of the exact likelihood from the
result gain more than d/2, or its gradient is more than 1 standard error long; numbers
``"gain"``, ``"decrement"``), ``"reduced_chi2"`` (far from 1; ``"value"`` and a likely
``"cause"``: ``"model_misfit"``, ``"noise_gain"``, ``"noise_read"``,
``"noise_overestimated"``), ``"truth_beyond_3se"`` (``"path"``, ``"z"``), ``"at_bound"``
(``"path"``, ``"bound"``), ``"stderr_undefined"`` (``"path"``) — and a ``"message"`` in
words; an empty list when nothing was found (absent in results written before flags
existed). ``"optimum_check"`` holds the local check's numbers (``null`` if it did not run)
and ``"objective"`` what the final fit maximised.

Non-finite numbers (an unconstrained parameter's stderr) are written as ``null``
and read back as NaN. Residual and model images are kept in memory only.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from invglare.errors import InputDataError
from invglare.files.atomic import write_json_atomic

FORMAT = "invglare.fit"
VERSION = 1


def _num(x: Any) -> float | None:
    """A float for JSON, ``None`` for NaN/inf (JSON has no such numbers)."""
    if x is None:
        return None
    v = float(x)
    return v if math.isfinite(v) else None


def _unnum(x: Any) -> float:
    return math.nan if x is None else float(x)


def _clean(obj: Any) -> Any:
    """Recursively replace non-finite floats by ``None`` and arrays by lists."""
    if isinstance(obj, dict):
        return {k: _clean(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_clean(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _clean(obj.tolist())
    if isinstance(obj, bool | np.bool_):
        return bool(obj)
    if isinstance(obj, int | np.integer):
        return int(obj)
    if isinstance(obj, float | np.floating):
        return _num(obj)
    return obj


@dataclasses.dataclass
class FitResult:
    """Parameters (physical units) with standard errors, and how the fit got there.

    **Attributes:**

    - `paths`: free parameter paths, in the order of the covariance.
    - `values`, `stderr`: ``{path: float}``; stderr is NaN for a parameter the data
      do not constrain.
    - `covariance`: ``(p, p)`` covariance of the physical values.
    - `nuisance`: the paths that are nuisance parameters.
    - `truth`: ``{path: float}`` when the target's ground truth is known, else None.
    - `loss`: ``sum(residuals**2)`` at the optimum (full resolution).
    - `reduced_chi2`: ``loss / (n_residuals - p)``.
    - `n_residuals`: residuals that depend on the parameters (masked pixels excluded).
    - `covariance_scale`: the ``s**2`` multiplying the inverse information (``(J^T J)^-1``).
    - `converged`, `message`: the final solve's status, in words.
    - `n_steps`: solver steps along the winning path, all stages.
    - `best_start`: index of the start that won the first stage.
    - `timing_s`: ``{"compile", "solve", "total"}`` seconds; compile is 0 when a
      compiled solve was reused (same shapes, settings and parameter space).
    - `solver`, `views`: settings used.
    - `stages`: per stage, per start: steps, final loss, status, loss history
      (the loss at each accepted step).
    - `starts`: starting values of the first stage, ``[{path: value}]``.
    - `objective`: what the final fit maximised, in words (the likelihood, or which views).
    - `flags`: when to distrust the result, ``[{"kind", "message", ...}]`` (see the
      module docstring and :mod:`invglare.fit.trust`); empty when none.
    - `optimum_check`: ``{"gain", "decrement", "steps"}`` of the local check of the
      likelihood's optimum, or None.
    - `residual_map`, `model_image`: ``(h, w)`` arrays (not saved): the
      noise-normalised residual ``(target - expected) / sigma`` (0 at clipped
      pixels) and the predicted photo.
    """

    paths: list[str]
    values: dict[str, float]
    stderr: dict[str, float]
    covariance: np.ndarray
    nuisance: list[str] = dataclasses.field(default_factory=list)
    truth: dict[str, float] | None = None
    loss: float = math.nan
    reduced_chi2: float = math.nan
    n_residuals: int = 0
    covariance_scale: float = 1.0
    converged: bool = False
    message: str = ""
    n_steps: int = 0
    best_start: int = 0
    timing_s: dict[str, float] = dataclasses.field(default_factory=dict)
    solver: str = "lm"
    views: dict[str, float] = dataclasses.field(default_factory=dict)
    stages: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    starts: list[dict[str, float]] = dataclasses.field(default_factory=list)
    objective: str = ""
    flags: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    optimum_check: dict[str, Any] | None = None
    #: The residuals' Jacobian in the latent space at the result, where the solve kept it
    #: (see :func:`invglare.fit.fit`); not saved.
    latent_jacobian: np.ndarray | None = dataclasses.field(default=None, repr=False, compare=False)
    residual_map: np.ndarray | None = dataclasses.field(default=None, compare=False, repr=False)
    model_image: np.ndarray | None = dataclasses.field(default=None, compare=False, repr=False)

    @property
    def loss_history(self) -> list[list[list[float]]]:
        """``[stage][start] -> [loss at each accepted step]``."""
        return [stage.get("loss_history", []) for stage in self.stages]

    def errors(self) -> dict[str, float]:
        """``value - truth`` for each parameter with a known truth (empty without truth)."""
        if not self.truth:
            return {}
        return {p: self.values[p] - self.truth[p] for p in self.paths if p in self.truth}

    def summary(self) -> str:
        """A plain-text table: parameter, value ± stderr, truth and error where known."""
        lines = [f"{self.message}", f"loss {self.loss:.6g}, reduced chi2 {self.reduced_chi2:.4g}"]
        if self.objective:
            lines.append(f"maximised: {self.objective}")
        lines += [f"  FLAG {f['kind']}: {f['message']}" for f in self.flags]
        for p in self.paths:
            line = f"  {p}: {self.values[p]:.6g} ± {self.stderr[p]:.3g}"
            if self.truth and p in self.truth:
                line += (
                    f"  (truth {self.truth[p]:.6g}, error {self.values[p] - self.truth[p]:+.3g})"
                )
            lines.append(line)
        return "\n".join(lines)

    # ---- JSON

    def to_dict(self) -> dict[str, Any]:
        params = {}
        for p in self.paths:
            entry: dict[str, Any] = {"value": self.values[p], "stderr": self.stderr[p]}
            if self.truth and p in self.truth:
                entry["truth"] = self.truth[p]
            entry["nuisance"] = p in self.nuisance
            params[p] = entry
        return _clean(
            {
                "format": FORMAT,
                "version": VERSION,
                "parameters": params,
                "covariance": {"paths": list(self.paths), "matrix": np.asarray(self.covariance)},
                "loss": self.loss,
                "reduced_chi2": self.reduced_chi2,
                "n_residuals": self.n_residuals,
                "covariance_scale": self.covariance_scale,
                "converged": self.converged,
                "message": self.message,
                "n_steps": self.n_steps,
                "best_start": self.best_start,
                "timing_s": dict(self.timing_s),
                "solver": self.solver,
                "views": dict(self.views),
                "objective": self.objective,
                "flags": list(self.flags),
                "optimum_check": self.optimum_check,
                "stages": list(self.stages),
                "starts": list(self.starts),
            }
        )

    def to_json(self, path: str | os.PathLike[str]) -> Path:
        """Write the result atomically as JSON (see the module docstring). **Returns:** the path."""
        return write_json_atomic(path, self.to_dict())

    @classmethod
    def from_dict(cls, data: Any, source: str = "the fit result") -> FitResult:
        """Rebuild a result from :meth:`to_dict` output; `InputDataError` if it is not one."""
        try:
            if not isinstance(data, dict) or data.get("format") != FORMAT:
                raise ValueError(f"it is not an {FORMAT!r} JSON object")
            params = data["parameters"]
            if not isinstance(params, dict) or not params:
                raise ValueError("'parameters' must be a non-empty object")
            paths = list(params)
            cov = data.get("covariance", {})
            matrix = np.array(
                [[_unnum(v) for v in row] for row in cov.get("matrix", [])], dtype=float
            )
            if cov.get("paths", paths) != paths or matrix.shape not in ((0,), (len(paths),) * 2):
                raise ValueError("'covariance' does not match 'parameters'")
            if matrix.shape == (0,):
                matrix = np.full((len(paths),) * 2, np.nan)
            truth = {p: float(e["truth"]) for p, e in params.items() if "truth" in e}
            return cls(
                paths=paths,
                values={p: _unnum(e["value"]) for p, e in params.items()},
                stderr={p: _unnum(e.get("stderr")) for p, e in params.items()},
                covariance=matrix,
                nuisance=[p for p, e in params.items() if e.get("nuisance", False)],
                truth=truth or None,
                loss=_unnum(data.get("loss")),
                reduced_chi2=_unnum(data.get("reduced_chi2")),
                n_residuals=int(data.get("n_residuals", 0)),
                covariance_scale=_unnum(data.get("covariance_scale", 1.0)),
                converged=bool(data["converged"]),
                message=str(data.get("message", "")),
                n_steps=int(data.get("n_steps", 0)),
                best_start=int(data.get("best_start", 0)),
                timing_s={k: _unnum(v) for k, v in data.get("timing_s", {}).items()},
                solver=str(data.get("solver", "lm")),
                views={k: float(v) for k, v in data.get("views", {}).items()},
                stages=list(data.get("stages", [])),
                starts=list(data.get("starts", [])),
                objective=str(data.get("objective", "")),
                flags=[dict(f) for f in data.get("flags", [])],
                optimum_check=data.get("optimum_check"),
            )
        except (KeyError, TypeError, ValueError, AttributeError) as err:
            what = f"missing key {err}" if isinstance(err, KeyError) else str(err)
            raise InputDataError(f"{source} is not a valid fit result: {what}") from None

    @classmethod
    def from_json(cls, path: str | os.PathLike[str]) -> FitResult:
        """Read a result written by :meth:`to_json`.

        Raises :class:`~invglare.errors.InputDataError` if the file is missing,
        unreadable, not JSON, or not a fit result.
        """
        p = Path(path)
        try:
            text = p.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise InputDataError(f"fit result {p} does not exist") from None
        except (OSError, UnicodeDecodeError) as err:
            raise InputDataError(f"cannot read fit result {p}: {err}") from None
        try:
            data = json.loads(text)
        except json.JSONDecodeError as err:
            raise InputDataError(
                f"fit result {p} is not valid JSON (line {err.lineno}, column {err.colno}: "
                f"{err.msg}); it may be truncated or corrupt"
            ) from None
        return cls.from_dict(data, source=f"fit result {p}")
