"""`NarrowLinear` (F_a's input layer with padded and reoriented backward products) against `nn.Linear` with the same
parameters: values and every gradient in float64, float32 to rounding, and the plain path where it does not apply."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from framework.model.narrow_linear import NarrowLinear


def _pair(in_features: int, out_features: int, bias: bool, dtype: torch.dtype) -> tuple[nn.Linear, NarrowLinear]:
    torch.manual_seed(in_features * 31 + out_features)
    plain = nn.Linear(in_features, out_features, bias=bias, dtype=dtype)
    narrow = NarrowLinear(in_features, out_features, bias=bias, dtype=dtype)
    narrow.load_state_dict(plain.state_dict())  # same keys as nn.Linear: checkpoints load either way
    return plain, narrow


@pytest.mark.parametrize(
    ("in_features", "out_features"),
    [(9, 128), (27, 32), (3, 5), (20, 20), (16, 64)],  # F_a's input, F_dw's input, narrow, square, fewer inputs
)
@pytest.mark.parametrize("bias", [True, False])
def test_values_and_gradients_equal_nn_linear_float64(in_features, out_features, bias):
    plain, narrow = _pair(in_features, out_features, bias, torch.float64)
    g = torch.Generator().manual_seed(in_features)
    x = torch.randn(37, in_features, generator=g, dtype=torch.float64, requires_grad=True)
    proj = torch.randn(37, out_features, generator=g, dtype=torch.float64)
    out_plain, out_narrow = plain(x), narrow(x)
    assert "NarrowLinear" in type(out_narrow.grad_fn).__name__  # the reoriented path was taken
    torch.testing.assert_close(out_narrow, out_plain, rtol=0, atol=0)  # the forward is torch's own
    grads_plain = torch.autograd.grad((out_plain * proj).sum(), [x, *plain.parameters()])
    grads_narrow = torch.autograd.grad((out_narrow * proj).sum(), [x, *narrow.parameters()])
    for a, b in zip(grads_narrow, grads_plain, strict=True):
        assert a.shape == b.shape
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)


def test_weight_gradient_alone_and_gradcheck():
    """An input without gradient (F_a's features may be fixed codes) and finite differences through the padding."""
    plain, narrow = _pair(9, 16, True, torch.float64)
    x = torch.randn(11, 9, dtype=torch.float64)
    (narrow(x) ** 2).sum().backward()
    (plain(x) ** 2).sum().backward()
    torch.testing.assert_close(narrow.weight.grad, plain.weight.grad, rtol=0, atol=1e-12)
    torch.testing.assert_close(narrow.bias.grad, plain.bias.grad, rtol=0, atol=1e-12)
    x.requires_grad_()
    assert torch.autograd.gradcheck(narrow, (x,))


def test_float32_to_rounding_and_plain_without_gradients():
    plain, narrow = _pair(9, 128, True, torch.float32)
    x = torch.randn(500, 9, requires_grad=True)
    torch.testing.assert_close(narrow(x), plain(x), rtol=0, atol=0)
    (narrow(x) ** 2).sum().backward()
    grads = [x.grad.clone(), narrow.weight.grad.clone()]
    x.grad = None
    (plain(x) ** 2).sum().backward()
    torch.testing.assert_close(grads[0], x.grad, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(grads[1], plain.weight.grad, rtol=1e-5, atol=1e-4)
    with torch.no_grad():
        out = narrow(x)
    assert out.grad_fn is None and out.is_contiguous()
    torch.testing.assert_close(out, plain(x).detach(), rtol=0, atol=0)


def test_wide_layers_keep_torchs_linear():
    """An input width that is a multiple of 16, with no fewer inputs than outputs, is already fast: no Python
    backward (F_a's head, its trunk)."""
    for shape in [(32, 32), (128, 11)]:
        _, narrow = _pair(*shape, True, torch.float32)
        out = narrow(torch.randn(4, shape[0], requires_grad=True))
        assert "NarrowLinear" not in type(out.grad_fn).__name__
