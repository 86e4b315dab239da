"""IEEE float32 arithmetic with the same bits on every CPU, for emulating a GPU kernel's rounding in tests.

torch's float32 kernels differ between machines (FMA contraction, vector width, reduction order), so an emulation
written with float32 tensors rounds differently on an AVX-512 and an AVX2 CPU. Here every value is a float64 tensor
holding a float32 number, and every single operation is computed in float64 and rounded to float32 at once. float64
carries more than 2 p + 2 bits of a float32's p, so that double rounding equals float32's own correctly rounded +, -,
*, / and sqrt (no FMA contraction): elementwise float64 operations are exact IEEE on every x86-64 CPU, so the result
is too. Autograd flows through the roundings (their backward is the identity, rounded to float32 the same way).
"""

from __future__ import annotations

import torch
from torch import Tensor


def f32(x: Tensor) -> Tensor:
    """x rounded to the nearest float32, kept as float64: the rounding step after each emulated operation."""
    return x.to(torch.float32).to(torch.float64)


def mul(a: Tensor | float, b: Tensor | float) -> Tensor:
    return f32(torch.as_tensor(a, dtype=torch.float64) * b)


def add(a: Tensor | float, b: Tensor | float) -> Tensor:
    return f32(torch.as_tensor(a, dtype=torch.float64) + b)


def sub(a: Tensor | float, b: Tensor | float) -> Tensor:
    return f32(torch.as_tensor(a, dtype=torch.float64) - b)


def div(a: Tensor | float, b: Tensor | float) -> Tensor:
    return f32(torch.as_tensor(a, dtype=torch.float64) / b)


def matmul(a: Tensor, b: Tensor) -> Tensor:
    """[..., I, K] @ [..., K, J] as glm's `operator*`: each product rounded, then summed left to right over k with a
    rounding after every addition (zero products included, as the kernel computes them)."""
    products = f32(a[..., :, :, None] * b[..., None, :, :])  # [..., I, K, J]
    out = products[..., 0, :]
    for k in range(1, a.shape[-1]):
        out = f32(out + products[..., k, :])
    return out  # [..., I, J]
