"""Fit the daylight eye to its bundled synthetic photo with torch optimisers, through GlarePSF.

The photo (``data_synthetic/eye_daylight.exr``, 256² px at 0.003 deg/px, core clipped at
60000 counts) was rendered from ``examples/eye_daylight.toml`` with a 2.8 mm pupil, 37
upper lashes at a mean angle of 3 deg, and a source 0.31 / -0.22 px off centre. This
script recovers the eye from the photo the way a PyTorch user would: the eye's PSF is a
:class:`invglare.torch.GlarePSF` layer whose pupil diameter, lash count and lash angle
are ``nn.Parameter`` s (in the fit's latent space, so the bounds of
``fits/eye_daylight.toml`` hold), the camera (flux, background, sub-pixel centre) is a
second ``nn.Parameter``, and the loss is invglare's own observation model and views,
reached through :func:`invglare.torch.from_jax`. The steps follow the fit config:

1. from the model config's eye (3 mm, 0 deg) with four lash counts across the bounds,
   ``torch.optim.Adam`` on the statistics that do not depend on where each lash's streak
   speckles (the radial profile and the angular energy), the centre held at the photo's
   core; the lowest of the four goes on (from one count, 40.3, Adam settled at 41.4 lashes
   for the truth's 37, and the pixel stage could not leave that basin);
2. ``torch.optim.LBFGS`` on the pixels (noise-normalised residuals, censored at the clip),
   everything free.

The result is printed next to invglare's own solver (Levenberg-Marquardt from a scan of
64 starts) on the same photo: the committed ``reports/eye_daylight/params.json``, or a
fresh run with ``--run-invglare`` (a few minutes).

Run: ``python examples/torch_fit.py`` (about a minute or two on a 2-core machine).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import torch

from invglare.config.fit import load_fit
from invglare.fit import Parameter, ParameterSpace
from invglare.fit.views import ViewContext, build_view
from invglare.torch import GlarePSF, from_jax, to_jax, to_torch

ROOT = Path(__file__).resolve().parents[1]
FIT_CONFIG = ROOT / "fits" / "eye_daylight.toml"
COMMITTED = ROOT / "reports" / "eye_daylight" / "params.json"
#: The eye's free parameters, with the bounds of fits/eye_daylight.toml.
EYE = ("pupil.diameter_mm", "upper_lashes.count", "upper_lashes.mean_angle_deg")


class PhotoLoss:
    """A loss of the photo given a PSF tensor and the camera's latent values (JAX, bridged).

    The camera is invglare's :class:`~invglare.fit.Observation` (flux, background,
    sub-pixel shift, soft clip) with the free fields of `space`; the loss is the sum of
    squares of the weighted views, as invglare's solver minimises it.
    """

    def __init__(self, setup, space: ParameterSpace, views: dict[str, float], held=None):
        obs = setup.forward.obs
        for name, value in (held or {}).items():  # fields this stage does not fit
            obs = eqx.tree_at(lambda o, n=name: getattr(o, n), obs, jnp.asarray(value))
        target = jnp.asarray(setup.target)
        built = {
            name: build_view(name, setup.view_options.get(name), target.shape, obs, setup.target)
            for name in views
        }
        self.space = space
        self.weights = {name: math.sqrt(w) for name, w in views.items()}
        self.views = built
        consts = (obs, target, obs.saturated_mask(target))
        self.fn = from_jax(self._loss, consts=consts, name="photo loss")

    def _loss(self, consts, psf, camera_latent):
        obs, target, saturated = consts
        obs = self.space.apply(obs, self.space.from_latent(camera_latent))
        expected = obs.expected(psf[0])
        h, w = target.shape
        centre = (w // 2 + obs.dx_px, h // 2 + obs.dy_px)
        ctx = ViewContext(target, saturated, expected, obs.clip(expected), obs, centre)
        r = jnp.concatenate([self.weights[n] * v(ctx) for n, v in self.views.items()])
        return jnp.sum(r * r)

    def __call__(self, psf: torch.Tensor, camera_latent: torch.Tensor) -> torch.Tensor:
        return self.fn(psf, camera_latent)


def _camera_space(setup, names: tuple[str, ...], start: dict[str, float]) -> ParameterSpace:
    """The camera's free fields (paths relative to the Observation), bounds from the config."""
    by_path = {p.path: p for p in setup.space.all}
    return ParameterSpace(
        [
            Parameter(n, by_path[f"obs.{n}"].lower, by_path[f"obs.{n}"].upper, init=start[n])
            for n in names
        ]
    )


def _latent_parameter(space: ParameterSpace) -> torch.nn.Parameter:
    """An ``nn.Parameter`` of the space's initial latent values (its own memory: an
    optimiser writes it in place, and JAX's buffer must not change)."""
    return torch.nn.Parameter(to_torch(space.initial_latent()).clone())


def _physical(space: ParameterSpace, latent: torch.Tensor) -> dict[str, float]:
    return space.as_dict(space.from_latent(to_jax(latent)))


def torch_fit(
    adam_steps: int = 60, lbfgs_steps: int = 30, verbose: bool = True, n_counts: int = 4
) -> dict:
    """Run both stages; return ``{"values", "truth", "loss", "seconds", "history"}``.

    Everything runs in float64, as ``invglare fit`` does: the config's arrays are read in
    float64 and the layers are built in it (the bridge would scope float64 calls by itself,
    but the fit's own objects are made here too).
    """
    with jax.enable_x64(True):
        return _torch_fit(adam_steps, lbfgs_steps, verbose, n_counts)


def _torch_fit(adam_steps: int, lbfgs_steps: int, verbose: bool, n_counts: int) -> dict:
    setup = load_fit(FIT_CONFIG)
    t0 = time.perf_counter()
    bounds = {p.path: (p.lower, p.upper) for p in setup.space.all}
    # The eye starts from the model config (as the photo's truth was set apart from it);
    # the camera from the photo's own guesses (flux, background, the core's centre).
    free = [
        {"path": f"model.aperture.{p}", "lower": bounds[f"model.aperture.{p}"][0],
         "upper": bounds[f"model.aperture.{p}"][1]}
        for p in EYE
    ]  # fmt: skip
    psf = GlarePSF(setup.forward.model, free, dtype=torch.float64)
    eye0 = psf.values()
    guess = dict(zip(setup.space.paths, np.asarray(setup.starts)[0], strict=True))
    camera0 = {n: float(guess[f"obs.{n}"]) for n in ("flux", "background", "dx_px", "dy_px")}
    history = []

    def log(stage, k, loss):
        history.append((stage, k, loss.item()))
        if verbose and (k % 10 == 0):
            shown = ", ".join(f"{p.rsplit('.', 1)[-1]}={v:.4g}" for p, v in psf.values().items())
            print(f"  {stage} {k:3d}: loss {loss.item():.6g}  {shown}", flush=True)

    # Stage 1: radial + angular views, the centre held; Adam from one lash count in each
    # quarter of the count's bounds (these views are multimodal in the count), keeping the
    # lowest loss. Each count is a stratum's centre: never an integer, where a relaxed
    # count has no gradient (its step is flat there).
    space1 = _camera_space(setup, ("flux", "background"), camera0)
    held = {"dx_px": camera0["dx_px"], "dy_px": camera0["dy_px"]}
    loss1 = PhotoLoss(setup, space1, {"radial": 1.0, "angular": 1.0}, held)
    lower, upper = bounds["model.aperture.upper_lashes.count"]
    best = None
    for j in range(n_counts):
        count = lower + (j + 0.5) * (upper - lower) / n_counts
        psf.set_values({**eye0, "aperture.upper_lashes.count": count})
        cam1 = _latent_parameter(space1)
        adam = torch.optim.Adam([psf.latent, cam1], lr=0.05)
        for k in range(adam_steps):
            adam.zero_grad()
            loss = loss1(psf(), cam1)
            loss.backward()
            adam.step()
            log(f"adam{j}", k, loss)
        with torch.no_grad():
            final1 = loss1(psf(), cam1).item()
        if best is None or final1 < best[0]:
            best = (final1, psf.values(), cam1.detach().clone())
    _, eye1, cam1 = best
    psf.set_values(eye1)

    # Stage 2: pixels, everything free; L-BFGS.
    cam_values = _physical(space1, cam1)
    space2 = _camera_space(setup, ("flux", "background", "dx_px", "dy_px"),
                           {**camera0, **cam_values})  # fmt: skip
    cam2 = _latent_parameter(space2)
    loss2 = PhotoLoss(setup, space2, {"pixels": 1.0})
    lbfgs = torch.optim.LBFGS([psf.latent, cam2], lr=1.0, max_iter=lbfgs_steps,
                              line_search_fn="strong_wolfe", tolerance_change=1e-12,
                              tolerance_grad=1e-9)  # fmt: skip
    calls = [0]

    def closure():
        lbfgs.zero_grad()
        loss = loss2(psf(), cam2)
        loss.backward()
        log("lbfgs", calls[0], loss)
        calls[0] += 1
        return loss

    lbfgs.step(closure)
    with torch.no_grad():
        final = loss2(psf(), cam2).item()
    camera = _physical(space2, cam2)
    values = {f"model.aperture.{p}": v for p, v in zip(EYE, psf.values().values(), strict=True)}
    values |= {f"obs.{n}": v for n, v in camera.items()}
    return {
        "values": values,
        "truth": setup.truth,
        "loss": final,
        "n_residuals": int(setup.target.size),
        "seconds": time.perf_counter() - t0,
        "evaluations": {"adam": n_counts * adam_steps, "lbfgs": calls[0]},
        "history": history,
    }


def invglare_fit() -> tuple[dict[str, float], str]:
    """invglare's own solver on the same config (a few minutes)."""
    from invglare.commands.fit import fit_setup

    with jax.enable_x64(True):
        setup = load_fit(FIT_CONFIG)
        t0 = time.perf_counter()
        result = fit_setup(setup)
    return dict(result.values), f"run now, {time.perf_counter() - t0:.0f} s"


def committed_fit() -> tuple[dict[str, float], str]:
    data = json.loads(COMMITTED.read_text())
    values = {p: entry["value"] for p, entry in data["parameters"].items()}
    return values, f"committed {COMMITTED.relative_to(ROOT)}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--adam-steps", type=int, default=60)
    parser.add_argument("--lbfgs-steps", type=int, default=30)
    parser.add_argument(
        "--run-invglare",
        action="store_true",
        help="run invglare's own fit now instead of reading the committed one",
    )
    args = parser.parse_args()
    print("torch fit (Adam on radial + angular, then L-BFGS on pixels):")
    out = torch_fit(args.adam_steps, args.lbfgs_steps)
    reference, source = invglare_fit() if args.run_invglare else committed_fit()
    truth = out["truth"] or {}
    print(
        f"\ntorch: {out['seconds']:.0f} s, {out['evaluations']} evaluations, loss "
        f"{out['loss']:.6g} over {out['n_residuals']} residuals; invglare: {source}\n"
    )
    print(
        "| parameter | truth | torch | error | invglare | error |\n|---|---:|---:|---:|---:|---:|"
    )
    for path, value in out["values"].items():
        t = truth.get(path, math.nan)
        ref = reference.get(path, math.nan)
        print(f"| `{path}` | {t:.6g} | {value:.6g} | {value - t:+.2e} | {ref:.6g} | "
              f"{ref - t:+.2e} |")  # fmt: skip


if __name__ == "__main__":
    main()
