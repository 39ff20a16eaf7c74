"""PyTorch interop: JAX functions as torch autograd functions, glare layers, an augmentation.

Everything here runs invglare's own JAX code; PyTorch sees tensors in and tensors out.

- :func:`from_jax` / :class:`JaxFunction`: any JAX function as a differentiable torch
  callable (DLPack in and out, a jitted ``jax.vjp`` for the backward pass);
  :func:`to_jax` and :func:`to_torch` are the zero-copy conversions it uses.
- :class:`GlarePSF`: a glare model's PSF as a tensor, its free parameters (chosen by path,
  as a fit's ``[[free]]``) an ``nn.Parameter`` in the fit's latent space.
- :class:`Glare`: glare on a batch of linear HDR images ``(B, C, H, W)``, by convolution for
  shift-invariant models and per-light billboards (or lens ghosts) otherwise.
- :class:`GlareAugment` and :class:`GlareDataset`: glare drawn per sample from ranges of eye
  or camera parameters, reproducible under a seed, also in a ``DataLoader`` with workers.

Install the extra first: ``pip install 'invglare[torch]'``. See ``docs/torch.md``.
"""

try:
    import torch as _torch  # noqa: F401  (the guard: everything below needs it)
except ImportError as _err:  # pragma: no cover - exercised in a subprocess by the tests
    raise ImportError(
        "invglare.torch needs PyTorch, which is not installed: pip install 'invglare[torch]' "
        "(for a CPU-only machine, install torch from the CPU wheel index first)"
    ) from _err

from invglare.torch._augment import GlareAugment as GlareAugment
from invglare.torch._augment import GlareDataset as GlareDataset
from invglare.torch._bridge import JaxFunction as JaxFunction
from invglare.torch._bridge import from_jax as from_jax
from invglare.torch._bridge import to_jax as to_jax
from invglare.torch._bridge import to_torch as to_torch
from invglare.torch._layers import Glare as Glare
from invglare.torch._layers import GlarePSF as GlarePSF

__all__ = [
    "Glare",
    "GlareAugment",
    "GlareDataset",
    "GlarePSF",
    "JaxFunction",
    "from_jax",
    "to_jax",
    "to_torch",
]
