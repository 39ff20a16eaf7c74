"""A few training steps of a tiny deglaring CNN on invglare's glare augmentation.

Each training image is a small procedural HDR scene (a dim, smoothly lit background and a
few point lights a hundred to a few thousand times brighter); ``GlareAugment`` with
``examples/torch_augment.toml`` puts on it the glare of a randomly drawn eye (pupil size,
lash count and angle, cornea cells) or camera (f-number, blade count and rotation,
cross-screen angles and spacing). The network sees the glared image and learns to
predict the clean one, in log units (HDR values span decades). The loss falls from the
do-nothing baseline (the glared image taken as the answer) within a few dozen steps.

Run: ``python examples/torch_deglare.py`` (under a minute on a 2-core CPU, most of it
compiling the two glare models once). ``--workers 2`` loads through a ``DataLoader`` with
two spawned workers (each compiles the models again: slower for a run this short).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch
from torch import nn
from torch.utils.data import DataLoader

from invglare.torch import GlareAugment, GlareDataset

CONFIG = Path(__file__).resolve().parent / "torch_augment.toml"


def scenes(n: int, size: int = 48, seed: int = 0) -> torch.Tensor:
    """`n` linear HDR scenes ``(n, 3, size, size)``: a lit background and 1-3 point lights."""
    g = torch.Generator().manual_seed(seed)
    y, x = torch.meshgrid(torch.linspace(-1, 1, size), torch.linspace(-1, 1, size), indexing="ij")
    out = []
    for _ in range(n):
        tilt = torch.rand(3, generator=g) * 2 - 1
        tint = 0.5 + torch.rand(3, 1, 1, generator=g)
        base = 0.1 * tint * (1.2 + tilt[0] * x + tilt[1] * y + 0.3 * torch.cos(3 * tilt[2] * x))
        for _ in range(int(torch.randint(1, 4, (1,), generator=g))):
            r, c = (int(v) for v in torch.randint(8, size - 8, (2,), generator=g))
            base[:, r, c] += 10.0 ** (2 + 1.5 * torch.rand(1, generator=g)) * tint[:, 0, 0]
        out.append(base.clamp_min(1e-3))
    return torch.stack(out)


class TinyDeglare(nn.Module):
    """Three convolutions predicting a log-domain correction (a residual on the input)."""

    def __init__(self, width: int = 16):
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(3, width, 5, padding=2),
            nn.ReLU(),
            nn.Conv2d(width, width, 5, padding=4, dilation=2),
            nn.ReLU(),
            nn.Conv2d(width, 3, 3, padding=1),
        )

    def forward(self, log_glared: torch.Tensor) -> torch.Tensor:
        return log_glared + self.net(log_glared)


def train(steps: int = 40, batch: int = 8, workers: int = 0, verbose: bool = True) -> dict:
    """Train `steps` steps; return the losses of the baseline, the first and the last steps."""
    torch.manual_seed(0)
    t0 = time.perf_counter()
    augment = GlareAugment(CONFIG, seed=0, return_clean=True)
    data = GlareDataset(scenes(steps * batch), augment)
    loader = DataLoader(
        data,
        batch_size=batch,
        shuffle=True,
        num_workers=workers,
        multiprocessing_context="spawn" if workers else None,
        generator=torch.Generator().manual_seed(1),
    )
    model = TinyDeglare()
    optimiser = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses, baselines = [], []
    for step, sample in enumerate(loader):
        # Log units; the clamp keeps FFT round-off below a dim pixel from reaching log(0).
        glared = torch.log(sample["glared"].clamp_min(1e-4))
        clean = torch.log(sample["clean"].clamp_min(1e-4))
        loss = nn.functional.mse_loss(model(glared), clean)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        losses.append(loss.item())
        baselines.append(nn.functional.mse_loss(glared, clean).item())
        if verbose and (step % 5 == 0 or step == steps - 1):
            print(f"  step {step:3d}: loss {losses[-1]:.4f} (glared as is: {baselines[-1]:.4f}), "
                  f"{time.perf_counter() - t0:.0f} s")  # fmt: skip
    return {
        "baseline": sum(baselines) / len(baselines),
        "first": sum(losses[:5]) / 5,
        "last": sum(losses[-5:]) / 5,
        "seconds": time.perf_counter() - t0,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--workers", type=int, default=0)
    args = parser.parse_args()
    out = train(args.steps, args.batch, args.workers)
    print(
        f"mean log-domain MSE: glared as is {out['baseline']:.4f}; network, first 5 steps "
        f"{out['first']:.4f}, last 5 steps {out['last']:.4f} ({out['seconds']:.0f} s)"
    )


if __name__ == "__main__":
    main()
