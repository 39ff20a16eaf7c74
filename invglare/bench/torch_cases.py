"""Benchmark cases of the PyTorch layers against the same JAX calls: the bridge's overhead.

Each torch case has a JAX twin calling the very programs the layer runs (the bridge's
jitted ``jax_forward``, ``jax_vjp`` and ``jax_backward``, with JAX arrays), so the
difference between the two is what the layer adds: validation (dtype, device, shape and
the non-finite check), DLPack in and out, and PyTorch's autograd bookkeeping. The goal is
at most 10 % + 0.2 ms over the twin at 256² and 512².

- ``torch_psf`` / ``torch_psf_jax``: :class:`~invglare.torch.GlarePSF` of the disk model of
  :mod:`invglare.bench.cases` (a 4 mm pupil on an N/2 raster, FFT to N x N), its diameter
  free, without a gradient;
- ``torch_psf_grad`` / ``torch_psf_grad_jax``: the same forward with ``jax.vjp``'s
  residuals, then the backward pass of a weighted sum (fixed random weights);
- ``torch_glare`` / ``torch_glare_jax``: :class:`~invglare.torch.Glare` of that model on one
  N x N RGB image: the PSF and the padded FFT convolution, one compiled call;
- ``torch_glare_grad`` / ``torch_glare_grad_jax``: forward and backward of a weighted sum,
  gradients for the image and the diameter.

:data:`PAIRS` maps each torch case to its twin; :func:`overhead_rows` turns a run's
records into the overhead table. ``python -m invglare.bench.torch_cases`` times every
pair side by side (calls alternating, so the machine's load falls on both alike) and
prints that table. torch is imported only inside the cases: importing this module does
not need it. Both ``invglare bench`` and this module's ``main`` run them with
``OMP_WAIT_POLICY=PASSIVE`` unless the environment sets it (:func:`passive_openmp`): on a
machine with few cores PyTorch's spinning OpenMP threads otherwise slow XLA's
(docs/torch.md, "Threads on a CPU"), which is no cost of the bridge.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable

import numpy as np

from invglare.bench.cases import Case, _disk_model
from invglare.bench.timing import load_1m, measure_together

#: The free parameter of the bench layers, with bounds that stay inside the raster window.
_FREE = [{"path": "aperture.shapes[0].diameter_mm", "lower": 3.0, "upper": 4.1}]
#: The overhead goal: torch time <= (1 + RELATIVE) * JAX time + ABSOLUTE_MS.
GOAL_RELATIVE = 0.10
GOAL_ABSOLUTE_MS = 0.2


def _torch():
    try:
        import torch
    except ImportError:
        return None
    return torch


def passive_openmp() -> str:
    """``OMP_WAIT_POLICY`` as the torch cases will run with it: PASSIVE unless already set.

    OpenMP reads it once, when PyTorch is first imported, so it is set only before that
    (a process that imported torch already keeps what it had).
    """
    if "torch" not in sys.modules:
        os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    return os.environ.get("OMP_WAIT_POLICY", "")


def _weights(shape: tuple[int, ...], seed: int) -> np.ndarray:
    return np.random.default_rng(seed).random(shape).astype(np.float32)


def _tensor(array: np.ndarray):
    """A torch-owned copy: numpy's buffers are 16-byte aligned, XLA's CPU wants 64 (JAX
    would copy them on every call, which a tensor made by torch does not need)."""
    import torch

    return torch.from_numpy(array).clone()


def _psf_layer(n: int):
    from invglare.torch import GlarePSF

    return GlarePSF(_disk_model(n), _FREE)


def _psf(n: int):
    torch = _torch()
    if torch is None:
        return None
    layer = _psf_layer(n)

    def run():
        with torch.no_grad():
            return layer()

    return run


def _psf_jax_inputs(n: int):
    """The PSF layer's bridge, its constant leaves and its latent as a JAX array."""
    from invglare.torch import to_jax

    layer = _psf_layer(n)
    bridge = layer._psf
    return bridge, bridge.consts_for(False), to_jax(layer.latent)


def _psf_jax(n: int):
    if _torch() is None:
        return None
    bridge, leaves, latent = _psf_jax_inputs(n)
    return lambda: bridge.jax_forward(leaves, latent)


def _psf_grad(n: int):
    torch = _torch()
    if torch is None:
        return None
    layer = _psf_layer(n)
    w = _tensor(_weights((1, n, n), 1))

    def run():
        layer.latent.grad = None
        layer().backward(w)
        return layer.latent.grad

    return run


def _psf_grad_jax(n: int):
    if _torch() is None:
        return None
    import jax.numpy as jnp

    bridge, leaves, latent = _psf_jax_inputs(n)
    w = jnp.asarray(_weights((1, n, n), 1))

    def run():
        _, vjp, _ = bridge.jax_vjp((True,), leaves, latent)
        return bridge.jax_backward(vjp, (w,))

    return run


def _glare_layer(n: int):
    from invglare.torch import Glare

    return Glare(_disk_model(n), _FREE)


def _image(n: int) -> np.ndarray:
    return (np.random.default_rng(2).random((1, 3, n, n)) * 10).astype(np.float32)


def _glare(n: int):
    torch = _torch()
    if torch is None:
        return None
    layer, image = _glare_layer(n), _tensor(_image(n))

    def run():
        with torch.no_grad():
            return layer(image)

    return run


def _glare_jax_inputs(n: int):
    """The Glare layer's compiled bridge, its constant leaves, latent and image, in JAX."""
    import jax.numpy as jnp

    from invglare.torch import to_jax

    layer = _glare_layer(n)
    bridge = layer._psf_convolve
    return bridge, bridge.consts_for(False), to_jax(layer.psf.latent), jnp.asarray(_image(n))


def _glare_jax(n: int):
    if _torch() is None:
        return None
    bridge, leaves, latent, image = _glare_jax_inputs(n)
    return lambda: bridge.jax_forward(leaves, latent, image)


def _glare_grad(n: int):
    torch = _torch()
    if torch is None:
        return None
    layer = _glare_layer(n)
    image = _tensor(_image(n)).requires_grad_()
    w = _tensor(_weights((1, 3, n, n), 3))

    def run():
        layer.psf.latent.grad = image.grad = None
        layer(image).backward(w)
        return layer.psf.latent.grad, image.grad

    return run


def _glare_grad_jax(n: int):
    if _torch() is None:
        return None
    import jax.numpy as jnp

    bridge, leaves, latent, image = _glare_jax_inputs(n)
    w = jnp.asarray(_weights((1, 3, n, n), 3))

    def run():
        _, vjp, _ = bridge.jax_vjp((True, True), leaves, latent, image)
        return bridge.jax_backward(vjp, (w,))

    return run


_PSF = "GlarePSF of the disk model (4 mm pupil, N/2 raster, FFT to N), diameter free"
_GLARE = "Glare of the disk model on one N x N RGB image: PSF + padded FFT convolution"
_SAME = "the same jitted JAX programs called with JAX arrays (the twin of {})"


def _twins(
    name: str,
    description: str,
    make: Callable[[int], Callable[[], object] | None],
    make_jax: Callable[[int], Callable[[], object] | None],
    forward: str | None = None,
) -> tuple[Case, Case]:
    """A torch case and its JAX twin (`name` + ``_jax``), the pair :data:`PAIRS` compares."""
    forward_jax = None if forward is None else f"{forward}_jax"
    return (
        Case(name, "pipeline", description, make, forward=forward),
        Case(f"{name}_jax", "pipeline", _SAME.format(name), make_jax, forward=forward_jax),
    )


TORCH_CASES: tuple[Case, ...] = (
    *_twins("torch_psf", f"{_PSF}, no gradient", _psf, _psf_jax),
    *_twins(
        "torch_psf_grad",
        f"{_PSF}: forward + backward of sum(w * PSF)",
        _psf_grad,
        _psf_grad_jax,
        forward="torch_psf",
    ),
    *_twins("torch_glare", f"{_GLARE}, no gradient", _glare, _glare_jax),
    *_twins(
        "torch_glare_grad",
        f"{_GLARE}: forward + backward of sum(w * out), image and diameter",
        _glare_grad,
        _glare_grad_jax,
        forward="torch_glare",
    ),
)

#: torch case -> its JAX twin.
PAIRS: dict[str, str] = {
    c.name: f"{c.name}_jax" for c in TORCH_CASES if not c.name.endswith("_jax")
}


def overhead_rows(records: list[dict], stat: str = "median_ms") -> list[dict]:
    """Per torch case and size: both times, their ratio, the excess (ms), the goal met.

    `records` are the runner's (``case``, ``size``, ``median_ms``, ``min_ms``); `stat`
    picks the time compared. Pairs with a side missing are left out.
    """
    by_key = {(r["case"], r["size"]): r for r in records}
    rows = []
    for case, twin in PAIRS.items():
        for size in sorted({r["size"] for r in records if r["case"] == case}):
            t, j = by_key.get((case, size)), by_key.get((twin, size))
            if t is None or j is None:
                continue
            torch_ms, jax_ms = t[stat], j[stat]
            rows.append(
                {
                    "case": case,
                    "size": size,
                    "torch_ms": torch_ms,
                    "jax_ms": jax_ms,
                    "ratio": round(torch_ms / jax_ms, 3),
                    "excess_ms": round(torch_ms - jax_ms, 3),
                    "goal_met": torch_ms <= (1 + GOAL_RELATIVE) * jax_ms + GOAL_ABSOLUTE_MS,
                }
            )
    return rows


def overhead_markdown(records: list[dict]) -> list[str]:
    """The overhead tables (markdown lines) of a run's records; empty without torch pairs."""
    lines = []
    for stat in ("median_ms", "min_ms"):
        rows = overhead_rows(records, stat)
        if not rows:
            continue
        lines += [
            "## PyTorch layers against the same JAX calls" if not lines else "",
            "",
            f"{stat.split('_')[0].capitalize()} times, each torch case timed together with "
            "its twin, their calls alternating. Goal: torch <= "
            f"{1 + GOAL_RELATIVE:g} x JAX + {GOAL_ABSOLUTE_MS:g} ms.",
            "",
            "| case | N | torch ms | JAX ms | ratio | excess ms | goal |",
            "|---|---:|---:|---:|---:|---:|---|",
        ]
        for r in rows:
            lines.append(
                f"| {r['case']} | {r['size']} | {r['torch_ms']:.3f} | {r['jax_ms']:.3f} | "
                f"{r['ratio']:.3f} | {r['excess_ms']:+.3f} | "
                f"{'met' if r['goal_met'] else 'missed'} |"
            )
    return lines


def main(argv: list[str] | None = None) -> list[dict]:
    """Time every pair side by side at the given sizes; print and return the overhead rows."""
    parser = argparse.ArgumentParser(description="PyTorch layers against the same JAX calls")
    parser.add_argument("sizes", nargs="*", type=int, default=[256, 512])
    parser.add_argument("--repeats", type=int, default=30)
    args = parser.parse_args(argv)
    passive_openmp()
    makers = {c.name: c.make for c in TORCH_CASES}
    records = []
    for n in args.sizes:
        for case, twin in PAIRS.items():
            a, b = makers[case](n), makers[twin](n)
            if a is None or b is None:
                print(f"skipping {case}: torch is not installed")
                continue
            timings = measure_together((a, b), args.repeats)
            records += [
                {"case": name, "size": n, "median_ms": t.median_ms, "min_ms": t.min_ms}
                for name, t in zip((case, twin), timings, strict=True)
            ]
    print(f"load average (1 min): {load_1m()}")
    print("\n".join(overhead_markdown(records)))
    return overhead_rows(records)


if __name__ == "__main__":
    main()
