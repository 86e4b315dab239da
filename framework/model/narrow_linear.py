"""A linear layer whose backward products take the shape the CPU's BLAS runs fastest: F_a's 9-wide input layer.

Why: F_a's feature input (the 9-dim latent code to 128) runs its backward products at a fraction of the wide layers'
rate when torch orients them the default way. On a 2-core AVX-512 VM (MKL, 8000 Gaussians, medians of 31, in cache):
- the weight gradient dY^T X ([128, 8000] x [8000, 9]) took 1.21 ms, and as (X^T dY)^T 0.25 ms: the product is fast
  when its output has the narrow side first;
- the input gradient dY W ([8000, 128] x [128, 9]) 0.81 ms, and with W's 9 columns padded to 16 0.22 ms (the padded
  columns' outputs are dropped).
F_a's forward+backward went from 15.4 to 14.6 ms (41 alternating rounds; 15.0 against 15.7 ms with the cache evicted
in between). The forward stays torch's, so F_a's values are bit for bit nn.Linear's. F_dw keeps torch's layers: its
56000-row products are bound by memory in a training step, and there the padded and reoriented ones were slower (1.9
-> 2.5 ms for its input layer's weight gradient).

`NarrowLinear` is `nn.Linear` (same parameters, state-dict keys and initialisation) whose backward, on CPU float
tensors, pads an input width that is not a multiple of 16 and takes the weight gradient in the faster orientation.
The gradients are the plain layer's up to the BLAS's summation order (`tests/test_narrow_linear.py`). Elsewhere (no
gradients, other devices, wide layers) it is the plain layer.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn import functional

from framework.runtime import cpu_float

#: widths are padded up to a multiple of this (16 float32 lanes: one AVX-512 register)
LANES = 16


def _padded(n: int) -> int:
    return -(-n // LANES) * LANES


class _NarrowLinearFunction(torch.autograd.Function):
    """x [M, in], weight [out, in], bias [out] -> x weight^T + bias [M, out]."""

    @staticmethod
    def forward(ctx, x, weight, bias):  # type: ignore[override]
        ctx.save_for_backward(x, weight)
        ctx.has_bias = bias is not None
        return functional.linear(x, weight, bias)  # torch's own product: the values are nn.Linear's bit for bit

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):  # type: ignore[override]
        x, weight = ctx.saved_tensors
        out_features, in_features = weight.shape
        grad_x = grad_w = grad_b = None
        if ctx.needs_input_grad[0]:
            if in_features % LANES:
                w = weight.new_zeros(out_features, _padded(in_features))  # the extra columns' outputs are dropped
                w[:, :in_features] = weight
                grad_x = grad_out.mm(w)[:, :in_features]  # [M, in] (a view of [M, in padded])
            else:
                grad_x = grad_out.mm(weight)
        if ctx.needs_input_grad[1]:
            # the product's output narrow side first: [in, out] when in < out
            grad_w = x.t().mm(grad_out).t() if in_features < out_features else grad_out.t().mm(x)  # [out, in]
        if ctx.has_bias and ctx.needs_input_grad[2]:
            grad_b = grad_out.sum(0)
        return grad_x, grad_w, grad_b


def _takes(x: Tensor, weight: Tensor) -> bool:
    """Whether the reoriented products apply: a narrow input (a width not a multiple of LANES, or fewer inputs than
    outputs), a 2-D CPU float input, and gradients wanted. Other layers keep torch's linear (no Python backward)."""
    out_features, in_features = weight.shape
    return (
        (in_features % LANES or in_features < out_features)
        and torch.is_grad_enabled()
        and (x.requires_grad or weight.requires_grad)
        and x.dim() == 2
        and cpu_float(x)  # CPU float32/64, and the CPU-only paths not switched off (a GPU's code on a CPU)
    )


class NarrowLinear(nn.Linear):
    """`nn.Linear` whose CPU training products are padded and oriented for the BLAS (see the module's docstring)."""

    def forward(self, x: Tensor) -> Tensor:
        if _takes(x, self.weight):
            return _NarrowLinearFunction.apply(x, self.weight, self.bias)
        return super().forward(x)
