"""The JAX -> torch bridge: gradients, complex conventions, memory sharing, layouts, errors."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
from helpers import x64

import invglare.torch._bridge as bridge_module
from invglare.errors import ConfigError, InputDataError
from invglare.render.convolve import convolve_psf
from invglare.torch import from_jax, to_jax, to_torch


def _f64(*shape, seed=0, grad=True):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(*shape, dtype=torch.float64, generator=g).requires_grad_(grad)


# --------------------------------------------------------------------------------------
# gradients


def test_gradcheck_two_inputs_float64():
    f = from_jax(lambda x, y: jnp.sin(x) * y + jnp.exp(0.1 * x * y))
    assert torch.autograd.gradcheck(f, (_f64(3, 4), _f64(3, 4, seed=1)))


def test_gradcheck_batched_along_leading_axis():
    # fn is written for one sample; in_axes batches x and shares w.
    f = from_jax(lambda x, w: jnp.tanh(x @ w), in_axes=(0, None))
    x, w = _f64(5, 3), _f64(3, 2, seed=1)
    assert f(x, w).shape == (5, 2)
    assert torch.autograd.gradcheck(f, (x, w))


def test_gradcheck_tuple_outputs():
    f = from_jax(lambda x: (jnp.sum(x**2), jnp.cos(x)))
    s, c = f(_f64(4))
    assert s.shape == () and c.shape == (4,)
    assert torch.autograd.gradcheck(f, (_f64(4),))


@pytest.mark.parametrize(
    "fn",
    [
        lambda z: jnp.abs(z) ** 2 * z + 1j * jnp.conj(z),  # C -> C, not holomorphic
        lambda z: jnp.real(z * z) + jnp.abs(z),  # C -> R
    ],
    ids=["c_to_c", "c_to_r"],
)
def test_complex_inputs_follow_pytorch_convention(fn):
    z = torch.randn(5, dtype=torch.complex128, generator=torch.Generator().manual_seed(2))
    assert torch.autograd.gradcheck(from_jax(fn), (z.requires_grad_(),))


def test_real_to_complex_follows_pytorch_convention():
    f = from_jax(lambda x: x * (1.0 + 2.0j) + x**2)
    assert torch.autograd.gradcheck(f, (_f64(4),))


def test_complex_gradient_equals_native_torch():
    # For L = |z|^2 PyTorch's gradient is 2 z (JAX's cotangent is 2 conj(z)).
    z = torch.tensor([1.0 + 2.0j, -0.5 + 0.25j], dtype=torch.complex128, requires_grad=True)
    from_jax(lambda z: jnp.sum(jnp.abs(z) ** 2))(z).backward()
    torch.testing.assert_close(z.grad, 2 * z.detach(), rtol=1e-12, atol=0)
    w = z.detach().clone().requires_grad_()
    torch.sum(torch.abs(w) ** 2 * w.real).backward()
    v = z.detach().clone().requires_grad_()
    from_jax(lambda z: jnp.sum(jnp.abs(z) ** 2 * jnp.real(z)))(v).backward()
    torch.testing.assert_close(v.grad, w.grad, rtol=1e-12, atol=0)


def test_torch_gradients_equal_jax_gradients():
    """A convolution (the Glare layer's core) through the bridge vs jax.vjp, 1e-6 relative."""
    rng = np.random.default_rng(3)
    image = rng.random((12, 10, 3))
    psf = rng.random((7, 5, 3))
    weights = rng.random((12, 10, 3))
    f = from_jax(convolve_psf)
    ti, tp = (torch.tensor(a, requires_grad=True) for a in (image, psf))
    out = f(ti, tp)
    out.backward(torch.tensor(weights))
    with x64():
        y, vjp = jax.vjp(convolve_psf, jnp.asarray(image), jnp.asarray(psf))
        gi, gp = vjp(jnp.asarray(weights))
    np.testing.assert_allclose(out.detach().numpy(), np.asarray(y), rtol=1e-12)
    np.testing.assert_allclose(ti.grad.numpy(), np.asarray(gi), rtol=1e-6)
    np.testing.assert_allclose(tp.grad.numpy(), np.asarray(gp), rtol=1e-6)


def test_only_inputs_needing_a_gradient_are_differentiated():
    f = from_jax(lambda x, y: x * y)
    x, y = _f64(3), _f64(3, seed=1, grad=False)
    f(x, y).sum().backward()
    assert y.grad is None
    torch.testing.assert_close(x.grad, y)


# --------------------------------------------------------------------------------------
# precision and compilation


def test_float64_without_global_x64_stays_float64():
    assert not jax.enable_x64.value
    x = torch.tensor([1.0, 1.0 + 1e-12], dtype=torch.float64)
    out = from_jax(lambda x: x - 1.0)(x)
    assert out.dtype == torch.float64
    np.testing.assert_allclose(out.numpy(), [0.0, 1e-12], rtol=1e-3, atol=0)
    assert not jax.enable_x64.value  # the scope was local


def test_float32_stays_float32():
    x = torch.randn(4, requires_grad=True)
    out = from_jax(lambda x: x * 2)(x)
    out.sum().backward()
    assert out.dtype == torch.float32 and x.grad.dtype == torch.float32


def test_compiled_once_per_shape_and_dtype():
    f = from_jax(lambda x: jnp.sin(x) * 2)
    with torch.no_grad():
        f(torch.randn(3))
        f(torch.randn(3))
        assert f.traces["forward"] == 1
        f(torch.randn(4))
        f(torch.randn(3, dtype=torch.float64))
        assert f.traces["forward"] == 3
    x = torch.randn(3, requires_grad=True)
    for _ in range(2):
        f(x).sum().backward()
    assert f.traces["vjp"] == 1 and f.traces["backward"] == 1


def test_constants_are_arguments_cast_to_the_call_precision():
    consts = {"scale": jnp.asarray(2.0), "n": jnp.asarray(3)}
    f = from_jax(lambda c, x: x * c["scale"] + c["n"], consts=consts)
    out32 = f(torch.ones(2))
    out64 = f(torch.ones(2, dtype=torch.float64))
    assert out32.dtype == torch.float32 and out64.dtype == torch.float64
    np.testing.assert_array_equal(out64.numpy(), [5.0, 5.0])


# --------------------------------------------------------------------------------------
# memory


def test_to_jax_and_to_torch_share_memory_on_cpu():
    x = torch.randn(4, 5)
    a = to_jax(x)
    assert a.unsafe_buffer_pointer() == x.data_ptr()
    b = jnp.sin(a)
    t = to_torch(b)
    assert t.data_ptr() == b.unsafe_buffer_pointer()


@pytest.mark.parametrize(
    "make",
    [
        lambda: torch.randn(5, 4).T,
        lambda: torch.randn(2, 3, 4, 5).to(memory_format=torch.channels_last),
        lambda: torch.randn(2, 3, 1, 5).to(memory_format=torch.channels_last),
    ],
    ids=["transposed", "channels_last", "channels_last_height_1"],
)
def test_permuted_layouts_are_adopted_without_a_copy(make):
    x = make()
    a = to_jax(x)
    assert a.unsafe_buffer_pointer() == x.data_ptr()
    np.testing.assert_array_equal(np.asarray(a), x.numpy())


@pytest.mark.parametrize(
    "make",
    [
        lambda: torch.randn(6, 8)[:, ::2],
        lambda: torch.randn(4, 1).expand(4, 5),
        lambda: torch.randn(3, dtype=torch.complex64).conj(),
        lambda: torch.randn(3, dtype=torch.complex64).conj().imag,
    ],
    ids=["stepped", "broadcast", "conj_bit", "neg_bit"],
)
def test_views_jax_cannot_adopt_are_copied_with_the_right_values(make):
    x = make()
    np.testing.assert_array_equal(np.asarray(to_jax(x)), x.resolve_conj().resolve_neg().numpy())


def test_bridge_output_shares_the_jax_buffer(monkeypatch):
    seen = []

    def recording(array):
        tensor = to_torch(array)
        seen.append((array.unsafe_buffer_pointer(), tensor))
        return tensor

    monkeypatch.setattr(bridge_module, "to_torch", recording)
    f = from_jax(lambda x: x * 3.0)
    for grad in (False, True):
        out = f(torch.randn(8, requires_grad=grad))
        pointer, tensor = seen[0]
        assert out is tensor and out.data_ptr() == pointer
        seen.clear()


@pytest.mark.parametrize("layout", ["transposed", "channels_last", "stepped"])
def test_non_contiguous_inputs_give_the_contiguous_result(layout):
    base = torch.randn(2, 3, 6, 8, dtype=torch.float64)
    if layout == "transposed":
        x = base.transpose(2, 3).contiguous().transpose(2, 3)
    elif layout == "channels_last":
        x = base.to(memory_format=torch.channels_last)
    else:
        x = torch.randn(2, 3, 6, 16, dtype=torch.float64)[..., ::2]
        base = x.contiguous()
    assert not x.is_contiguous()
    f = from_jax(lambda a: jnp.cumsum(a, axis=-1) * jnp.arange(a.shape[-2])[:, None])
    xa, xb = x.clone().requires_grad_(), base.clone().requires_grad_()
    ya, yb = f(xa), f(xb)
    torch.testing.assert_close(ya, yb, rtol=0, atol=0)
    w = torch.randn_like(base)
    ya.backward(w)
    yb.backward(w)
    torch.testing.assert_close(xa.grad, xb.grad, rtol=0, atol=0)


def test_in_place_change_before_backward_is_refused():
    x = torch.randn(4, requires_grad=True)
    y = x * 1.0
    out = from_jax(jnp.exp)(y)
    with torch.no_grad():
        out.mul_(2.0)  # the output may alias a JAX residual
    with pytest.raises(RuntimeError, match="modified by an inplace operation"):
        out.sum().backward()


def test_second_order_derivatives_are_refused():
    x = _f64(3)
    out = from_jax(lambda x: jnp.sum(x**3))(x)
    with pytest.raises(RuntimeError, match="second derivatives"):
        torch.autograd.grad(out, x, create_graph=True)


# --------------------------------------------------------------------------------------
# bad input


@pytest.mark.parametrize("dtype", [torch.int64, torch.int32, torch.bool, torch.float16])
def test_non_float_tensors_are_refused(dtype):
    f = from_jax(lambda x: x * 2, names=("x",))
    with pytest.raises(InputDataError, match=r"input 0 \(x\) has dtype .*expected float32"):
        f(torch.ones(3, dtype=dtype))


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_values_are_refused_with_their_place(bad):
    x = torch.zeros(3, 4)
    x[1, 2] = bad
    with pytest.raises(InputDataError, match=r"1 non-finite .* first at index \(1, 2\)"):
        from_jax(lambda x: x)(x)


def test_non_finite_check_can_be_turned_off():
    out = from_jax(lambda x: x * 2, check_finite=False)(torch.tensor([float("nan")]))
    assert torch.isnan(out).all()


def test_shape_signature_names_what_was_expected():
    f = from_jax(lambda im, p: im * p[0], signature=("B 3 H W", "1"), names=("images", "p"))
    with pytest.raises(InputDataError, match=r"images\) has shape \(2, 4, 5, 5\); expected "):
        f(torch.ones(2, 4, 5, 5), torch.ones(1))
    with pytest.raises(InputDataError, match=r"\(p\) has shape \(2,\); expected \(1\)"):
        f(torch.ones(2, 3, 5, 5), torch.ones(2))
    with pytest.raises(InputDataError, match="takes 2 tensors"):
        f(torch.ones(2, 3, 5, 5))


def test_batched_inputs_must_agree_on_the_batch_size():
    f = from_jax(lambda a, b: a + b, in_axes=(0, 0))
    with pytest.raises(InputDataError, match="has 3 samples along axis 0, the inputs before it 2"):
        f(torch.ones(2, 4), torch.ones(3, 4))


def test_tensor_on_a_device_jax_lacks_is_refused():
    with pytest.raises(InputDataError, match=r"is on meta, but JAX here runs on cpu.*\.cpu\(\)"):
        from_jax(lambda x: x)(torch.ones(3, device="meta"))


def test_to_jax_of_float64_outside_x64_is_refused():
    with pytest.raises(InputDataError, match="enable_x64"):
        to_jax(torch.ones(2, dtype=torch.float64))
    with x64():
        assert to_jax(torch.ones(2, dtype=torch.float64)).dtype == jnp.float64


def test_non_tensor_and_integer_output_are_refused():
    with pytest.raises(InputDataError, match=r"must be a torch\.Tensor, got list"):
        from_jax(lambda x: x)([1.0, 2.0])
    with pytest.raises(ConfigError, match="output 0 is int32"):
        from_jax(lambda x: jnp.argmax(x))(torch.ones(3))
    with pytest.raises(ConfigError, match="in_axes entries must be 0 or None"):
        from_jax(lambda x: x, in_axes=(1,))


@pytest.mark.parametrize(
    "make",
    [
        lambda: torch.randn(3, 4),
        lambda: torch.randn(5, 4).T,
        lambda: torch.randn(2, 3, 4, 5).to(memory_format=torch.channels_last),
        lambda: torch.randn(101)[1:],  # not aligned for XLA: both copy
        lambda: torch.randn(3, dtype=torch.complex64),
    ],
    ids=["contiguous", "transposed", "channels_last", "unaligned", "complex"],
)
def test_direct_dlpack_import_equals_jax_from_dlpack(make):
    # The bridge calls jaxlib's import without jax.dlpack.from_dlpack's Python around it;
    # if a jaxlib update removed that entry point, the bridge would fall back (slower).
    assert bridge_module._FAST_IMPORT is not None, "jaxlib's DLPack import entry point moved"
    x = make()
    fast, public = bridge_module._FAST_IMPORT(x), jax.dlpack.from_dlpack(x)
    assert fast.dtype == public.dtype and fast.shape == public.shape
    np.testing.assert_array_equal(np.asarray(fast), np.asarray(public))
    shared = public.unsafe_buffer_pointer() == x.data_ptr()
    assert (fast.unsafe_buffer_pointer() == x.data_ptr()) == shared
