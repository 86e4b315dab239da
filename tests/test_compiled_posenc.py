"""The compiled positional encoding (`framework.kernels.posenc`) against the torch path of `posenc`: values and
gradients in float64, float32 to rounding, and arguments far from the unit box."""

from __future__ import annotations

import pytest
import torch

from framework.execution import TORCH
from framework.kernels.posenc import posenc_compiled
from framework.model.posenc import posenc, posenc_dim


@pytest.mark.parametrize(("shape", "num_freqs"), [((50, 7, 3), 4), ((40, 3), 1), ((9, 2), 6)])
def test_values_and_gradients_equal_the_torch_path_float64(shape, num_freqs):
    g = torch.Generator().manual_seed(num_freqs)
    x = (torch.rand(shape, generator=g, dtype=torch.float64) * 2.4 - 1.2).requires_grad_()  # a little past [-1, 1]
    x2 = x.detach().clone().requires_grad_()
    ours, ref = posenc_compiled(x, num_freqs), posenc(x2, num_freqs, TORCH)
    assert ours.shape == (*shape[:-1], posenc_dim(num_freqs, shape[-1]))
    torch.testing.assert_close(ours, ref, rtol=0, atol=1e-12)
    proj = torch.randn(ours.shape, generator=g, dtype=torch.float64)
    (ours * proj).sum().backward()
    (ref * proj).sum().backward()
    torch.testing.assert_close(x.grad, x2.grad, rtol=1e-12, atol=1e-11)


def test_float32_equals_torch_to_rounding_and_posenc_takes_it():
    """float32: both evaluate sin and cos of the same float32 arguments, so they agree to a few float32 ulps; far from
    the box (x = 40) too, where the highest frequency's argument is 2^5 pi 40."""
    g = torch.Generator().manual_seed(1)
    x = torch.cat([torch.rand(1000, 3, generator=g) * 2 - 1, torch.full((1, 3), 40.0)]).requires_grad_()
    x2 = x.detach().clone().requires_grad_()
    ours, ref = posenc(x, 6), posenc(x2, 6, TORCH)
    assert ours.dtype == torch.float32 and ours.grad_fn is not None and "PosEnc" in type(ours.grad_fn).__name__
    torch.testing.assert_close(ours, ref, rtol=0, atol=2e-6)
    ours.sum().backward()
    ref.sum().backward()
    torch.testing.assert_close(x.grad, x2.grad, rtol=1e-5, atol=2e-4)  # sums of 2^k pi-scaled terms, up to 100 pi


def test_gradcheck():
    x = (torch.rand(5, 3, dtype=torch.float64) * 2 - 1).requires_grad_()
    assert torch.autograd.gradcheck(lambda t: posenc_compiled(t, 3), (x,))


def test_zero_frequencies_and_other_devices_keep_torch():
    x = torch.rand(4, 3)
    assert torch.equal(posenc(x, 0), x)
    meta = torch.empty(4, 3, device="meta")
    assert posenc(meta, 2).shape == (4, 15)
