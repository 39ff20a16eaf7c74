"""The chain file: emcee's HDF5 backend written one step per file opening, and our metadata.

The format is emcee's group ``mcmc`` (chain, log_prob, blobs = the physical values,
accepted, random state, the iteration counter) and a group ``invglare`` whose attribute
``meta`` is a JSON record of the parameters, bounds, priors, the fit and every run. Every
completed step is on disk before the next one starts.

**One step, one transaction.** The iteration counter is the commit: everything a step
changes is stored where the counter selects it, so that whatever a kill leaves behind,
the counter describes a consistent chain. The step's rows (``chain``, ``log_prob``,
``blobs``, and its acceptance flags in ``accepted_steps``) go to row ``iteration``, its
random state to slot ``(iteration + 1) % 2`` of ``rng_keys`` / ``rng_scalars``; the file
is flushed; then the counter is raised and flushed. The acceptance counts are the sum of
the committed rows of ``accepted_steps``, the random state the committed slot. emcee's
own copies (``accepted``, ``random_state_*`` attributes) are written after the commit
and repaired from these at the next run, so emcee's readers see the same chain.

**Run records.** Each run appends its record to ``meta["runs"]`` when it starts
(``"stopped": "running"``, with its pid) and completes it when it ends (why it stopped,
``end_step``, ``n_steps``, all from the counter). A record still ``"running"`` whose
process is gone is a killed run: the next run closes it as ``"killed"`` at the step the
counter holds (its last complete step), and :func:`load_chain` shows it so.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from pathlib import Path
from typing import Any

import emcee
import h5py
import numpy as np

from invglare.errors import InputDataError
from invglare.files.atomic import pause_point, pid_alive
from invglare.fit.params import Parameter, ParameterSpace
from invglare.fit.result import FitResult
from invglare.fit.sample.diagnostics import diagnose
from invglare.fit.sample.posterior import SAMPLING_SPACE
from invglare.fit.sample.result import SampleResult
from invglare.fit.sample.signals import deferred_signals

#: Name of the emcee group in the HDF5 file, and of the group holding our metadata.
CHAIN_GROUP = "mcmc"
META_GROUP = "invglare"
FORMAT = "invglare.chain"
VERSION = 1

#: How long a writer waits for a file another process (a reader) holds locked.
LOCK_WAIT_S = 30.0
#: Per-step acceptance flags, and the two slots of the random state (see the docstring).
ACCEPTED_STEPS = "accepted_steps"
RNG_KEYS = "rng_keys"
RNG_SCALARS = "rng_scalars"
#: Stored in a run record while the run is going on (a kill leaves it so).
RUNNING = "running"


def _open_for_writing(path, mode: str = "a"):
    """``h5py.File(path, mode)``, waiting while another process holds the file's lock.

    HDF5 locks a file while it is open; a user peeking at the chain with h5py (or
    emcee's backend) while the sampler runs must not make the next step's write
    fail and end a long run.
    """
    deadline = time.monotonic() + LOCK_WAIT_S
    while True:
        try:
            return h5py.File(path, mode)
        except BlockingIOError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)


def read_chain(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """``(latent, physical blobs, log_prob, accepted, iteration)`` of the stored steps.

    Read without taking the file lock, so that reading a running chain never
    blocks the sampler's next write; only the first ``iteration`` steps (the
    counter is written last) are read, which are complete.
    """
    try:
        with h5py.File(path, "r", locking=False) as f:
            g = f[CHAIN_GROUP]
            it = int(g.attrs["iteration"])
            latent = g["chain"][:it]
            blobs = g["blobs"][:it] if "blobs" in g else np.full_like(latent, np.nan)
            return latent, blobs, g["log_prob"][:it], _accepted(g, it), it
    except (OSError, KeyError) as err:
        raise InputDataError(
            f"cannot read the chain file {path}: {err}; it is damaged or not an emcee chain"
        ) from None


def _accepted(g, iteration: int) -> np.ndarray:
    """Acceptance counts per walker of the first `iteration` (committed) steps."""
    if ACCEPTED_STEPS in g:
        return g[ACCEPTED_STEPS][:iteration].sum(axis=0).astype(float)
    return g["accepted"][...]  # a chain written before accepted_steps existed


def _random_state(g, iteration: int):
    """The random state after the committed step `iteration`, or None before the first."""
    if RNG_KEYS not in g:
        elements = [v for k, v in sorted(g.attrs.items()) if k.startswith("random_state_")]
        return elements or None
    if iteration == 0:
        return None
    slot = iteration % 2
    pos, has_gauss, cached = g[RNG_SCALARS][slot]
    return ("MT19937", g[RNG_KEYS][slot], int(pos), int(has_gauss), float(cached))


class ChainBackend(emcee.backends.HDFBackend):
    """emcee's HDF5 backend, writing a step in one file opening that Ctrl-C cannot tear.

    emcee's own `save_step` opens the file six times per step to validate shapes
    (``_check``); at ~2 ms per opening that cost more than the model on small
    photos. The shapes are fixed by the sampler that calls it, so this writes the
    same datasets and attributes, in the same order (the iteration counter last,
    so a step is only counted once all of it is there), with one opening, as one
    transaction (see the module docstring).
    """

    def open(self, mode="r"):
        if mode == "r":
            return super().open(mode)
        f = _open_for_writing(self.filename, mode)
        if not self.dtype_set and self.name in f and "chain" in f[self.name]:
            self.dtype = f[self.name]["chain"].dtype
            self.dtype_set = True
        return f

    @property
    def accepted(self):
        with self.open() as f:
            g = f[self.name]
            return _accepted(g, int(g.attrs["iteration"]))

    @property
    def random_state(self):
        with self.open() as f:
            g = f[self.name]
            return _random_state(g, int(g.attrs["iteration"]))

    def reset(self, nwalkers, ndim):
        with deferred_signals():
            super().reset(nwalkers, ndim)
            with self.open("a") as f:
                g = f[self.name]
                g.create_dataset(
                    ACCEPTED_STEPS, (0, nwalkers), maxshape=(None, nwalkers), dtype=np.uint8
                )
                g.create_dataset(RNG_KEYS, (2, 624), dtype=np.uint32)
                g.create_dataset(RNG_SCALARS, (2, 3), dtype=np.float64)

    def save_step(self, state, accepted):
        with deferred_signals(), self.open("a") as f:
            g = f[self.name]
            iteration = int(g.attrs["iteration"])
            g["chain"][iteration, :, :] = state.coords
            g["log_prob"][iteration, :] = state.log_prob
            if state.blobs is not None:
                g["blobs"][iteration, :] = state.blobs
            if ACCEPTED_STEPS not in g:  # a chain of an earlier version: as it was written
                g["accepted"][:] += accepted
                for i, v in enumerate(state.random_state):
                    g.attrs[f"random_state_{i}"] = v
                g.attrs["iteration"] = iteration + 1
                return
            g[ACCEPTED_STEPS][iteration, :] = accepted
            slot = (iteration + 1) % 2
            _, keys, pos, has_gauss, cached = state.random_state
            g[RNG_KEYS][slot] = keys
            g[RNG_SCALARS][slot] = (pos, has_gauss, cached)
            f.flush()  # the whole step is on disk before it is counted
            pause_point("chain-step")
            g.attrs["iteration"] = iteration + 1
            f.flush()
            _write_emcee_copies(g, iteration + 1)

    def grow(self, ngrow, blobs):
        with deferred_signals():
            super().grow(ngrow, blobs)
            with self.open("a") as f:
                g = f[self.name]
                if ACCEPTED_STEPS in g:
                    g[ACCEPTED_STEPS].resize(g["chain"].shape[0], axis=0)


def _write_emcee_copies(g, iteration: int) -> None:
    """emcee's ``accepted`` and ``random_state_*`` from the committed step `iteration`."""
    g["accepted"][:] = _accepted(g, iteration)
    state = _random_state(g, iteration)
    if state is not None:
        for i, v in enumerate(state):
            g.attrs[f"random_state_{i}"] = v


def repair_chain(path: Path) -> None:
    """Make emcee's own copies of the counters agree with the committed steps (after a kill
    between a step's commit and their update). Call it holding the report folder's lock."""
    with deferred_signals(), _open_for_writing(path) as f:
        if CHAIN_GROUP in f and ACCEPTED_STEPS in f[CHAIN_GROUP]:
            g = f[CHAIN_GROUP]
            _write_emcee_copies(g, int(g.attrs["iteration"]))


def read_meta(path: Path) -> dict[str, Any] | None:
    try:
        with h5py.File(path, "r", locking=False) as f:
            if META_GROUP not in f:
                return None
            return json.loads(f[META_GROUP].attrs["meta"])
    except (OSError, KeyError, ValueError) as err:
        raise InputDataError(
            f"cannot read the chain file {path}: {err}; it is damaged or not an invglare "
            "chain (move it away and sample again without resume)"
        ) from None


def write_meta(path: Path, meta: dict[str, Any]) -> None:
    with deferred_signals(), _open_for_writing(path) as f:
        g = f.require_group(META_GROUP)
        g.attrs["meta"] = json.dumps(meta)


def stored_iteration(path: Path) -> int:
    try:
        with h5py.File(path, "r", locking=False) as f:
            if CHAIN_GROUP not in f:
                return 0
            return int(f[CHAIN_GROUP].attrs["iteration"])
    except (OSError, KeyError) as err:
        raise InputDataError(
            f"cannot read the chain file {path}: {err}; it is damaged or not an emcee chain"
        ) from None


def close_killed_runs(meta: dict[str, Any], at_step: int) -> list[dict[str, Any]]:
    """Close the run records a killed run left ``"running"``: killed, ending at `at_step`
    (the counter when the next run starts). **Returns:** the records closed."""
    closed = []
    for run in meta.get("runs", []):
        if run.get("stopped") == RUNNING:
            run["stopped"] = "killed"
            run["end_step"] = int(at_step)
            run["n_steps"] = int(at_step) - int(run.get("start_step", 0))
            closed.append(run)
    return closed


def _shown_runs(runs: list[dict[str, Any]], iteration: int) -> list[dict[str, Any]]:
    """The run records as a reader sees them: a record "running" whose process is gone is
    a killed run ending at the counter (the file itself is left as it is)."""
    out = []
    for run in runs:
        pid = run.get("pid")
        if run.get("stopped") == RUNNING and not (isinstance(pid, int) and pid_alive(pid)):
            run = dict(run)
            close_killed_runs({"runs": [run]}, iteration)
        out.append(run)
    return out


def chain_meta(
    space: ParameterSpace, fit_result: FitResult, n_walkers: int, likelihood: str, fp: str
) -> dict[str, Any]:
    """A new chain's metadata: format, parameters, bounds and priors, the fit it starts from."""
    return {
        "format": FORMAT,
        "version": VERSION,
        "fingerprint": fp,
        "paths": list(space.paths),
        "nuisance": [p.path for p in space.nuisance],
        "sampling_space": SAMPLING_SPACE,
        "likelihood": likelihood,
        "n_walkers": int(n_walkers),
        "bounds": [
            {
                "path": p.path,
                "lower": p.lower,
                "upper": p.upper,
                "transform": p.kind,
                "prior": None if p.prior is None else dataclasses.asdict(p.prior),
                "fit_value": fit_result.values.get(p.path),
            }
            for p in space.all
        ],
        "truth": fit_result.truth,
        "fit_values": dict(fit_result.values),
        "fit_stderr": {k: (v if math.isfinite(v) else None) for k, v in fit_result.stderr.items()},
        "fit_converged": bool(fit_result.converged),
        "runs": [],
    }


def load_chain(
    path: str | os.PathLike[str], space: ParameterSpace | None = None, *, tau_factor: float = 50.0
) -> SampleResult:
    """Read a chain written by :func:`sample` and diagnose it.

    `space` (the fit's parameter space) is checked against the stored paths and
    used for the bound checks; without it the bounds stored in the file are used.
    Raises :class:`~invglare.errors.InputDataError` if the file is missing,
    damaged, empty, or for other parameters.
    """
    p = Path(path)
    if not p.is_file():
        raise InputDataError(f"chain file {p} does not exist; run invglare sample first")
    meta = read_meta(p)
    if meta is None or meta.get("format") != FORMAT:
        raise InputDataError(f"{p} is not an invglare chain (no {META_GROUP!r} metadata)")
    if space is not None and list(meta["paths"]) != list(space.paths):
        raise InputDataError(
            f"the chain {p} is for the parameters {meta['paths']} but the config frees "
            f"{list(space.paths)}: it is from another model or config"
        )
    if space is None:
        space = _space_from_meta(meta)
    if stored_iteration(p) == 0:
        raise InputDataError(f"the chain file {p} holds no completed step yet")
    latent, blobs, log_prob, accepted, iteration = read_chain(p)
    acceptance = accepted / iteration
    chain = np.asarray(blobs, dtype=float).reshape(latent.shape)
    tau, burn, thin, conv, notes = diagnose(
        chain, latent, log_prob, acceptance, space, tau_factor=tau_factor,
        n_nan=int(sum(r.get("n_nan", 0) for r in meta.get("runs", []))),
    )  # fmt: skip
    runs = _shown_runs(meta.get("runs", []), iteration)
    last = runs[-1] if runs else {}
    return SampleResult(
        paths=list(meta["paths"]),
        nuisance=list(meta.get("nuisance", [])),
        chain=chain,
        latent=latent,
        log_prob=log_prob,
        acceptance=acceptance,
        tau={q: float(t) for q, t in zip(meta["paths"], tau, strict=True)},
        burn_in=burn,
        thin=thin,
        converged=conv,
        warnings=notes,
        moves=[tuple(m) for m in last.get("moves", [("stretch", 1.0)])],
        tau_factor=tau_factor,
        runs=runs,
        truth=meta.get("truth"),
        fit_values=meta.get("fit_values", {}),
        fit_stderr=meta.get("fit_stderr", {}),
        timing=dict(last.get("timing", {})),
        sampling_space=meta.get("sampling_space", SAMPLING_SPACE),
        likelihood=meta.get("likelihood", "pixels"),
        path=p,
    )


def _space_from_meta(meta: dict[str, Any]) -> ParameterSpace:
    params, nuis = [], []
    for b in meta["bounds"]:
        lo, hi = float(b["lower"]), float(b["upper"])
        init = b.get("fit_value")
        if init is None or not (lo < init < hi):
            init = (
                0.5 * (lo + hi) if math.isfinite(lo + hi) else (lo + 1 if math.isfinite(lo) else 0)
            )
        par = Parameter(b["path"], lo, hi, init=init, transform=b["transform"])
        (nuis if b["path"] in meta.get("nuisance", []) else params).append(par)
    return ParameterSpace(params, nuis)
