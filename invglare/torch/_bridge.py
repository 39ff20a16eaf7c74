"""The bridge: a JAX function as a differentiable torch callable, through DLPack and ``jax.vjp``.

**Data path.** Tensors reach JAX through DLPack (:func:`to_jax`) and results come back the
same way (:func:`to_torch`):

- *zero-copy* for a CPU tensor in C order or any permutation of it (a transpose, a
  channels-last image): JAX adopts the buffer with its layout and rearranges it inside its
  own call where its program needs C order;
- *one contiguous copy* (``Tensor.contiguous``) for a view JAX cannot adopt: gaps (a slice
  with a step), broadcast axes (stride 0, e.g. ``expand``), and for views whose
  conjugate or negative bit is set (resolved first); JAX itself copies a buffer that is not
  aligned for XLA (a view starting at an odd element);
- results are JAX's own buffers handed to torch without a copy: the output tensor shares
  memory with the JAX array (checked by the tests).

**Compilation.** Each :class:`JaxFunction` holds three jitted programs, each compiled once
per input shape and dtype (and, for the backward pass, per set of inputs that need a
gradient): the forward pass alone (when no gradient is needed), the forward pass with
``jax.vjp``'s residuals (when one is), and the backward pass, which applies the saved
``jax.vjp`` to the incoming gradients. Nothing is recomputed in the backward pass.

**Precision.** float32 tensors are computed as float32. A float64 (or complex128) input
runs the call inside a local ``jax.enable_x64(True)`` scope (thread-local, undone on
return): no global default is changed, and without the scope JAX would silently turn a
float64 tensor into float32. Constants (``consts``, e.g. a model's arrays) follow the
call's precision: their float leaves are cast to float32 or float64 with the inputs.

**Complex numbers.** PyTorch's gradient of a real loss with respect to ``z`` is the
conjugate Wirtinger form ``dL/dx + i dL/dy``; JAX's cotangents are its conjugate. The
bridge conjugates at the boundary (the incoming gradient before ``jax.vjp``, the results
after), so a complex function behaves as a native PyTorch one (``gradcheck`` agrees).

**Devices.** CPU tensors go to JAX's CPU devices. A tensor on another device (CUDA, meta)
is refused with an error naming the device unless JAX here has a backend for it; nothing
is copied between devices behind the caller's back: move it with ``.cpu()`` explicitly.

**Safety.** The inputs and outputs are saved for the backward pass, so an in-place change
of either before ``backward()`` raises PyTorch's usual error instead of giving a silently
wrong gradient (the JAX residuals may alias both). The backward pass is
refused under ``create_graph=True``: a second-order derivative through the bridge is an
error, never a silently missing term.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import torch
from jax import dlpack as jax_dlpack
from jaxtyping import Array

from invglare.errors import ConfigError, InputDataError

__all__ = ["JaxFunction", "from_jax", "to_jax", "to_torch"]

#: Tensor dtypes the bridge takes; float16 and bfloat16 are not among invglare's precisions.
ACCEPTED_DTYPES = (torch.float32, torch.float64, torch.complex64, torch.complex128)
_WIDE = (torch.float64, torch.complex128)


# --------------------------------------------------------------------------------------
# conversions


def _precision(wide: bool):
    """A local float64 scope for a wide call (JAX would demote float64 to float32 without)."""
    return jax.enable_x64(True) if wide else contextlib.nullcontext()


def _adoptable(t: torch.Tensor) -> bool:
    """True when JAX can adopt the tensor's buffer as it is: C order or a permutation of it."""
    if t.is_contiguous():
        return True
    expected = 1
    # Axes of length 1 have no meaningful stride; the rest must tile the buffer exactly.
    for stride, size in sorted((s, n) for n, s in zip(t.shape, t.stride(), strict=True) if n != 1):
        if stride != expected:
            return False
        expected *= size
    return True


def _dlpack_import():
    """jaxlib's C++ DLPack import, the one ``jax.dlpack.from_dlpack`` ends in, or None.

    The public function spends 30-70 us of Python per tensor around that call (measured
    here on a 2-core CPU), a good part of the 0.2 ms the bridge may add to a call. For the
    dtypes the bridge takes, what it adds (a dtype canonicalisation that is the identity
    inside the precision scope, a placement on the same device) changes nothing, so the
    bridge calls the import directly and falls back to the public function where jaxlib
    has no such entry point (a test checks both give the same array on the same memory).
    """
    try:
        from jax._src.lib import _jax, jaxlib_extension_version
    except ImportError:  # pragma: no cover - another jaxlib layout
        return None
    entry = getattr(_jax, "dlpack_managed_tensor_to_buffer", None)
    if entry is None or jaxlib_extension_version < 467:  # pragma: no cover - older jaxlib
        return None
    cpu = jax.devices("cpu")[0]
    # 1 is DLPack's kDLCPU device type.
    return lambda t: entry(t.__dlpack__(), cpu, None, None, 1)


_FAST_IMPORT = _dlpack_import()


def to_jax(tensor: torch.Tensor) -> Array:
    """A JAX array of a torch tensor, without a copy where the layout allows (see the module).

    A float64 or complex128 tensor needs float64 in JAX: call this inside
    ``jax.enable_x64(True)`` (the bridge does that itself), otherwise an
    :class:`~invglare.errors.InputDataError` says so instead of a silent float32 array.

    **Example:**

    ```python
    x = torch.randn(4, 4)
    a = to_jax(x)          # shares x's memory: do not modify x while a is in use
    ```
    """
    if not isinstance(tensor, torch.Tensor):
        raise InputDataError(f"expected a torch.Tensor, got {type(tensor).__name__}")
    if tensor.dtype in _WIDE and not jax.enable_x64.value:
        raise InputDataError(
            f"a {tensor.dtype} tensor needs float64 in JAX: call to_jax inside "
            "`with jax.enable_x64(True):` (JAX would otherwise make it float32 silently)"
        )
    t = tensor.detach()
    if t.is_conj():
        t = t.resolve_conj()
    if t.is_neg():
        t = t.resolve_neg()
    if not _adoptable(t):
        t = t.contiguous()
    if _FAST_IMPORT is not None and t.device.type == "cpu":
        return _FAST_IMPORT(t)
    return jax_dlpack.from_dlpack(t)


def to_torch(array: Array) -> torch.Tensor:
    """A torch tensor of a JAX array, sharing its buffer (no copy; waits for the array).

    The tensor aliases memory JAX treats as immutable: clone it before changing it in place.

    **Example:**

    ```python
    t = to_torch(jnp.arange(3.0))   # tensor([0., 1., 2.])
    ```
    """
    return torch.from_dlpack(array)


# --------------------------------------------------------------------------------------
# checks


@functools.cache
def _jax_platforms() -> frozenset[str]:
    return frozenset(d.platform for d in jax.devices())


def _check_device(t: torch.Tensor, what: str) -> None:
    kind = t.device.type
    if kind == "cpu":
        return
    platforms = _jax_platforms()
    if kind == "cuda" and platforms & {"gpu", "cuda", "rocm"}:
        return
    raise InputDataError(
        f"{what} is on {t.device}, but JAX here runs on {', '.join(sorted(platforms))} only; "
        f"move it with .cpu() (and the result back with .to('{t.device}')), or install a JAX "
        "build for that device: invglare does not copy between devices on its own"
    )


def check_finite(t: torch.Tensor, what: str) -> None:
    """Raise :class:`~invglare.errors.InputDataError` naming the first NaN or infinite value."""
    finite = torch.isfinite(t.detach())
    if bool(finite.all()):
        return
    bad = ~finite
    first = tuple(int(i) for i in torch.nonzero(bad)[0])
    raise InputDataError(
        f"{what} has {int(bad.sum())} non-finite (NaN or inf) values, the first at index "
        f"{first}; replace or mask them first"
    )


def _parse_pattern(pattern) -> tuple | None:
    if pattern is None:
        return None
    tokens = pattern.split() if isinstance(pattern, str) else list(pattern)
    out = []
    for tok in tokens:
        if isinstance(tok, int | np.integer) or (isinstance(tok, str) and tok.isdigit()):
            out.append(int(tok))
        elif isinstance(tok, str) and tok.isidentifier():
            out.append(tok)
        else:
            raise ConfigError(
                f"shape pattern {pattern!r}: {tok!r} is neither an axis length nor an axis name"
            )
    return tuple(out)


def _show_pattern(pattern: tuple) -> str:
    return "(" + ", ".join(str(p) for p in pattern) + ")"


# --------------------------------------------------------------------------------------
# the function


class JaxFunction:
    """A JAX function of arrays as a differentiable torch callable.

    **Arguments:**

    - `fn`: a pure JAX function returning one array or a tuple of arrays (floating or
      complex). It is called as ``fn(*arrays)``, or ``fn(consts, *arrays)`` with `consts`.
    - `consts`: optional pytree (an equinox model, a photo) passed to `fn` in every call
      as JAX arrays, never differentiated, cast to each call's precision. Its arrays are
      arguments of the compiled programs, not constants baked into them.
    - `in_axes`: ``None`` (default) or one entry per input, ``0`` (batched along the
      leading axis: `fn` is written for one sample and ``jax.vmap``-ed) or ``None``
      (shared by the batch).
    - `signature`: optional shape pattern per input, e.g. ``("B C H W", "p")``: numbers
      are fixed axis lengths, names must agree across inputs. A mismatch is an
      :class:`~invglare.errors.InputDataError` naming the expected shape.
    - `names`: optional names of the inputs, used in errors.
    - `check_finite`: refuse NaN or infinite input values (default True). The check is one
      fused pass inside the compiled call (no extra pass over the tensors in PyTorch); a
      bad input raises before any result is handed back.
    - `name`: the function's name in errors (default: `fn`'s).

    **Returns:** a callable taking torch tensors (float32/float64/complex, on the CPU),
    returning a tensor or a tuple of tensors, differentiable by ``torch.autograd``.

    **Example:**

    ```python
    square_sum = JaxFunction(lambda x: jnp.sum(x**2, axis=-1), in_axes=(0,))
    x = torch.randn(8, 3, requires_grad=True)
    square_sum(x).sum().backward()      # x.grad == 2 * x
    ```
    """

    def __init__(
        self,
        fn: Callable[..., Any],
        *,
        consts: Any = None,
        in_axes: Sequence[int | None] | None = None,
        signature: Sequence[Any] | None = None,
        names: Sequence[str] | None = None,
        check_finite: bool = True,
        name: str | None = None,
    ):
        if not callable(fn):
            raise ConfigError(f"from_jax needs a callable, got {type(fn).__name__}")
        self.name = name or getattr(fn, "__name__", type(fn).__name__)
        self.check_finite = bool(check_finite)
        self._fn = fn
        self._has_consts = consts is not None
        dynamic, self._static = eqx.partition(consts, eqx.is_array)
        leaves, self._treedef = jax.tree_util.tree_flatten(dynamic)
        self._leaves: dict[bool, tuple] = {}
        self._given_leaves = tuple(leaves)
        self.in_axes = None if in_axes is None else tuple(in_axes)
        if self.in_axes is not None and any(a not in (0, None) for a in self.in_axes):
            raise ConfigError(f"{self.name}: in_axes entries must be 0 or None, got {in_axes}")
        self.signature = None if signature is None else tuple(_parse_pattern(p) for p in signature)
        n_in = [len(s) for s in (self.in_axes, self.signature, names) if s is not None]
        if len(set(n_in)) > 1:
            raise ConfigError(f"{self.name}: in_axes, signature and names give {n_in} inputs")
        self.n_inputs = n_in[0] if n_in else None
        self.names = None if names is None else tuple(names)
        #: Traces per program ("forward", "vjp", "backward"): one per shape, dtype and mask.
        self.traces = {"forward": 0, "vjp": 0, "backward": 0}
        self._single: bool | None = None
        self.jax_forward = jax.jit(self._counted("forward", self._forward))
        self.jax_vjp = jax.jit(self._counted("vjp", self._vjp), static_argnums=0)
        self.jax_backward = jax.jit(self._counted("backward", _pull_back))

    # ---- the traced functions

    def _counted(self, kind: str, f):
        @functools.wraps(f)
        def traced(*args):
            self.traces[kind] += 1  # runs while tracing only: one count per compilation
            return f(*args)

        return traced

    def _apply(self, leaves: tuple, *arrays):
        fn = self._fn
        if self._has_consts:
            consts = eqx.combine(jax.tree_util.tree_unflatten(self._treedef, leaves), self._static)
            fn = functools.partial(self._fn, consts)
        if self.in_axes is not None:
            fn = jax.vmap(fn, in_axes=self.in_axes)
        out = fn(*arrays)
        single = not isinstance(out, tuple | list)
        outs = (out,) if single else tuple(out)
        for i, o in enumerate(outs):
            if not (isinstance(o, jax.Array) and jnp.issubdtype(o.dtype, jnp.inexact)):
                raise ConfigError(
                    f"{self.name}: output {i} is {getattr(o, 'dtype', type(o).__name__)}; the "
                    "bridge returns floating or complex arrays only (pass integers as consts)"
                )
        if self._single is not None and self._single != single:
            raise ConfigError(f"{self.name}: returns an array for some shapes, a tuple for others")
        self._single = single
        return outs

    def _finite(self, arrays) -> Array:
        """Per input, whether every value is finite (one fused pass inside the program)."""
        if not self.check_finite:
            return jnp.zeros((0,), bool)
        return jnp.stack([jnp.all(jnp.isfinite(a)) for a in arrays])

    def _forward(self, leaves: tuple, *arrays):
        return self._apply(leaves, *arrays), self._finite(arrays)

    def _vjp(self, mask: tuple[bool, ...], leaves: tuple, *arrays):
        def of_differentiated(*diff):
            it = iter(diff)
            full = [next(it) if m else a for a, m in zip(arrays, mask, strict=True)]
            return self._apply(leaves, *full)

        diff = [a for a, m in zip(arrays, mask, strict=True) if m]
        out, vjp = jax.vjp(of_differentiated, *diff)
        return out, vjp, self._finite(arrays)

    def _refuse_non_finite(self, finite: Array, tensors) -> None:
        """Raise, naming the first NaN or infinity, unless every input was finite."""
        flags = np.asarray(finite)
        if flags.all():
            return
        i = int(np.argmin(flags))
        check_finite(tensors[i], self._what(i))
        raise InputDataError(f"{self._what(i)} has non-finite (NaN or inf) values")

    # ---- validation

    def _what(self, i: int) -> str:
        label = f" ({self.names[i]})" if self.names else ""
        return f"{self.name}: input {i}{label}"

    def check_inputs(self, tensors: Sequence[torch.Tensor]) -> None:
        """Raise :class:`~invglare.errors.InputDataError` for inputs the function cannot take."""
        if self.n_inputs is not None and len(tensors) != self.n_inputs:
            raise InputDataError(
                f"{self.name} takes {self.n_inputs} tensors"
                + (f" ({', '.join(self.names)})" if self.names else "")
                + f", got {len(tensors)}"
            )
        bound: dict[str, int] = {}
        for i, t in enumerate(tensors):
            what = self._what(i)
            if not isinstance(t, torch.Tensor):
                raise InputDataError(f"{what} must be a torch.Tensor, got {type(t).__name__}")
            if t.dtype not in ACCEPTED_DTYPES:
                raise InputDataError(
                    f"{what} has dtype {t.dtype}; expected float32 or float64 (or complex64 / "
                    "complex128): convert it with .float() or .double()"
                )
            _check_device(t, what)
            pattern = self.signature[i] if self.signature else None
            if pattern is not None:
                ok = t.ndim == len(pattern)
                for size, want in zip(t.shape, pattern, strict=False):
                    if not ok:
                        break
                    if isinstance(want, int):
                        ok = size == want
                    else:
                        ok = bound.setdefault(want, size) == size
                if not ok:
                    known = {k: v for k, v in bound.items() if k in pattern}
                    given = f" with {known}" if known else ""
                    raise InputDataError(
                        f"{what} has shape {tuple(t.shape)}; expected "
                        f"{_show_pattern(pattern)}{given}"
                    )
            if self.in_axes is not None and self.in_axes[i] == 0:
                if t.ndim == 0:
                    raise InputDataError(f"{what} is a scalar but is batched along axis 0")
                size = bound.setdefault("<batch>", t.shape[0])
                if size != t.shape[0]:
                    raise InputDataError(
                        f"{what} has {t.shape[0]} samples along axis 0, the inputs before it {size}"
                    )

    # ---- calls

    def consts_for(self, wide: bool) -> tuple:
        """The constants' leaves cast to the call's precision (cached per precision)."""
        if wide not in self._leaves:
            real, cplx = (jnp.float64, jnp.complex128) if wide else (jnp.float32, jnp.complex64)

            def cast(x):
                if jnp.issubdtype(x.dtype, jnp.complexfloating):
                    return x.astype(cplx)
                if jnp.issubdtype(x.dtype, jnp.floating):
                    return x.astype(real)
                return x

            with _precision(wide):
                self._leaves[wide] = tuple(cast(x) for x in self._given_leaves)
        return self._leaves[wide]

    def __call__(self, *tensors: torch.Tensor):
        self.check_inputs(tensors)
        wide = any(t.dtype in _WIDE for t in tensors)
        leaves = self.consts_for(wide)
        if torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
            mask = tuple(bool(t.requires_grad) for t in tensors)
            outs = _Bridge.apply(self, mask, wide, leaves, *tensors)
            outs = outs if isinstance(outs, tuple) else (outs,)
        else:
            with _precision(wide):
                out, finite = self.jax_forward(leaves, *(to_jax(t) for t in tensors))
            self._refuse_non_finite(finite, tensors)
            outs = tuple(to_torch(o) for o in out)
        return outs[0] if self._single else outs

    def __repr__(self) -> str:
        return f"JaxFunction({self.name}, traces={self.traces})"


def _pull_back(vjp, cotangents: tuple):
    # PyTorch's gradients are the conjugates of JAX's cotangents (see the module): conjugate
    # on the way in and out. For real arrays jnp.conj is the identity and compiles away.
    grads = vjp(tuple(jnp.conj(c) for c in cotangents))
    return tuple(jnp.conj(g) for g in grads)


class _Bridge(torch.autograd.Function):
    """The autograd node of a :class:`JaxFunction` call.

    The forward pass takes ``ctx`` itself (rather than a separate ``setup_context``):
    the residuals of ``jax.vjp`` are made there and must reach the backward pass, and
    they are no tensors that could travel as outputs.
    """

    @staticmethod
    def forward(ctx, bridge: JaxFunction, mask, wide: bool, leaves, *tensors):
        with _precision(wide):
            out, vjp, finite = bridge.jax_vjp(mask, leaves, *(to_jax(t) for t in tensors))
        bridge._refuse_non_finite(finite, tensors)
        outs = tuple(to_torch(o) for o in out)
        ctx.bridge, ctx.mask, ctx.wide, ctx.vjp = bridge, mask, wide, vjp
        # Saved only for PyTorch's version check: the residuals may alias these buffers.
        ctx.save_for_backward(*tensors, *outs)
        return outs if len(outs) > 1 else outs[0]

    @staticmethod
    def backward(ctx, *grads):
        if torch.is_grad_enabled():
            # create_graph=True: a graph of this backward pass would miss the second-order
            # terms through JAX. (``once_differentiable`` would run it without a graph and
            # hand back a constant where the incoming gradients need none: a silently
            # missing term, so the refusal is explicit here.)
            raise RuntimeError(
                f"{ctx.bridge.name}: second derivatives (create_graph=True) through a JAX "
                "function are not supported; compute them in JAX (jax.hessian, jax.jvp)"
            )
        ctx.saved_tensors  # noqa: B018  (raises if an input or output was modified in place)
        with _precision(ctx.wide):
            cotangents = tuple(to_jax(g) for g in grads)
            pulled = ctx.bridge.jax_backward(ctx.vjp, cotangents)
        it = iter(pulled)
        per_input = [to_torch(next(it)) if m else None for m in ctx.mask]
        return (None, None, None, None, *per_input)


def from_jax(fn: Callable[..., Any] | None = None, **options: Any):
    """A :class:`JaxFunction` of `fn` (see there for `options`); also a decorator.

    **Example:**

    ```python
    @from_jax(in_axes=(0, None))
    def shifted(x, offset):
        return jnp.sin(x) + offset

    y = shifted(torch.randn(8, 16), torch.tensor(0.5))
    ```
    """
    if fn is None:
        return functools.partial(from_jax, **options)
    return JaxFunction(fn, **options)
