"""`framework.model.posenc.posenc` on the CPU as a compiled loop (numba) with a hand-written backward.

Why: F_dw encodes the seven L_w points of every Gaussian each training step, [8000, 7, 3] at 4 frequencies. In torch
that is a product, a sine and a cosine per frequency and a concatenation, and the backward evaluates every sine and
cosine once more.
The frequencies are powers of two, so one sine and one cosine per coordinate give all of them by the double-angle
identities, sin 2a = 2 sin a cos a and cos 2a = (cos a - sin a)(cos a + sin a), in float64; the backward replays the
same recurrence from the saved pair instead of reading the [M, 27] encoding back. Both paths are bound by memory:
the [M, 27] encoding is written once forward and its gradient read once backward (vectorising the recurrence over
blocks of rows gained little).

Same values as the torch path: torch's argument at frequency k, (2^k pi) x in the input's dtype, is 2^k times its
argument at frequency 0 exactly (a power of two scales without rounding), so both evaluate sin and cos of the same
numbers; here from the float64 pair at frequency 0, to float64 accuracy, stored in the input's dtype
(`tests/test_compiled_posenc.py` compares values and gradients with the torch path in float64).
"""

from __future__ import annotations

import math

import torch
from numba import njit
from torch import Tensor


@njit(cache=True, nogil=True)
def encode(x, sin0, cos0, num_freqs, out) -> None:
    """out [M, D (1 + 2F)] = [x, sin f0, cos f0, ..., sin f(F-1), cos f(F-1)] (blocks of D) from x [M, D] and the
    sine and cosine of pi x, sin0 and cos0 [M, D] (float64)."""
    M, D = x.shape
    for m in range(M):
        for j in range(D):
            out[m, j] = x[m, j]
            s, c = sin0[m, j], cos0[m, j]
            for k in range(num_freqs):
                base = D * (1 + 2 * k)
                out[m, base + j] = s
                out[m, base + D + j] = c
                s, c = 2.0 * s * c, (c - s) * (c + s)


@njit(cache=True, nogil=True)
def encode_backward(grad, sin0, cos0, num_freqs, grad_x) -> None:
    """grad [M, D (1 + 2F)] -> grad_x [M, D]: the identity block plus, per frequency k, 2^k pi (g_sin cos - g_cos sin)
    with the sines and cosines replayed from sin0, cos0 [M, D]."""
    M, D = grad_x.shape
    for m in range(M):
        for j in range(D):
            acc = grad[m, j]
            s, c = sin0[m, j], cos0[m, j]
            scale = math.pi
            for k in range(num_freqs):
                base = D * (1 + 2 * k)
                acc += scale * (grad[m, base + j] * c - grad[m, base + D + j] * s)
                s, c = 2.0 * s * c, (c - s) * (c + s)
                scale *= 2.0
            grad_x[m, j] = acc


class _PosEnc(torch.autograd.Function):
    """x [M, D] -> [M, D (1 + 2F)]."""

    @staticmethod
    def forward(ctx, x, num_freqs):  # type: ignore[override]
        x = x.detach().contiguous()
        arg = (math.pi * x).double()  # torch's frequency-0 argument, rounded as it rounds it
        sin0, cos0 = torch.sin(arg), torch.cos(arg)  # [M, D] float64
        out = x.new_empty(x.shape[0], x.shape[1] * (1 + 2 * num_freqs))
        encode(x.numpy(), sin0.numpy(), cos0.numpy(), num_freqs, out.numpy())
        ctx.save_for_backward(sin0, cos0)
        ctx.num_freqs, ctx.dtype = num_freqs, x.dtype
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):  # type: ignore[override]
        sin0, cos0 = ctx.saved_tensors
        grad_x = sin0.new_empty(sin0.shape)
        encode_backward(grad.contiguous().numpy(), sin0.numpy(), cos0.numpy(), ctx.num_freqs, grad_x.numpy())
        return grad_x.to(ctx.dtype), None


def posenc_compiled(x: Tensor, num_freqs: int) -> Tensor:
    """`posenc(x, num_freqs)` for CPU float32/float64 x [..., D], differentiable in x."""
    if x.dim() == 2:
        return _PosEnc.apply(x, num_freqs)
    lead, D = x.shape[:-1], x.shape[-1]
    return _PosEnc.apply(x.reshape(-1, D), num_freqs).reshape(*lead, D * (1 + 2 * num_freqs))
