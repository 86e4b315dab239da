"""The best matrix-product rate this machine reaches: the denominator of the arithmetic lower bounds that
`tools/bench_train.py` (the training step) and `tools/bench_render.py` (the novel-pose frame) print.

A square float32 product is the shape BLAS runs most efficiently; the MLPs' skinny products run slower. So an MLP's
FLOPs divided by this rate is a time no implementation on this hardware's BLAS goes below. Machines differ 2-3x, so a
bound is only read against times measured in the same run.

`record_gemms` and `replay_gemms` give a second, tighter reference: the very products a computation runs (the same
shapes and strides, forward and backward), timed alone with fresh operands. What a computation takes beyond them is
not matrix arithmetic (bias, activations, autograd); what they take is the BLAS's rate at those shapes.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch.utils._python_dispatch import TorchDispatchMode

from framework.evaluation.frame_timing import synchronize


def gemm_rate(repeats: int, device: torch.device | str, size: int = 2048) -> list[float]:
    """GFLOP/s of `repeats` float32 size x size matrix products (after two warm-up products), one rate per product."""
    gen = torch.Generator().manual_seed(2)
    a, b = (torch.rand(size, size, generator=gen).to(device) for _ in range(2))
    rates = []
    for i in range(repeats + 2):
        t = time.perf_counter()
        a @ b
        synchronize(device)
        if i >= 2:
            rates.append(2 * size**3 / ((time.perf_counter() - t) * 1e9))
    return rates


_GEMM_OPS = {torch.ops.aten.mm.default, torch.ops.aten.addmm.default, torch.ops.aten.bmm.default}


@dataclass(frozen=True)
class GemmCall:
    """One matrix product as a computation ran it: the aten op, its tensor operands' (shape, stride, dtype), and its
    scalar arguments (addmm's beta and alpha)."""

    op: object
    operands: tuple[tuple[tuple[int, ...], tuple[int, ...], torch.dtype], ...]
    scalars: dict

    @property
    def flops(self) -> int:
        *_, (a_shape, _, _), (b_shape, _, _) = self.operands
        return 2 * _prod(a_shape) * b_shape[-1]


def _prod(shape: tuple[int, ...]) -> int:
    out = 1
    for n in shape:
        out *= n
    return out


class _Recorder(TorchDispatchMode):
    def __init__(self) -> None:
        super().__init__()
        self.calls: list[GemmCall] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # noqa: ANN001
        kwargs = kwargs or {}
        if func in _GEMM_OPS:
            tensors = tuple((tuple(a.shape), tuple(a.stride()), a.dtype) for a in args if isinstance(a, torch.Tensor))
            self.calls.append(GemmCall(func, tensors, dict(kwargs)))
        return func(*args, **kwargs)


def record_gemms(fn: Callable[[], None]) -> list[GemmCall]:
    """Run `fn` once (forward and backward alike) and return every mm / addmm / bmm it dispatched, in order."""
    rec = _Recorder()
    with rec:
        fn()
    return rec.calls


def replay_gemms(calls: list[GemmCall], repeats: int, device: torch.device | str) -> list[float]:
    """ms of running `calls` back to back with fresh random operands of the recorded shapes and strides (after two
    warm-up passes), one time per pass: the products alone, without the work between them."""
    gen = torch.Generator().manual_seed(3)

    def operand(shape: tuple[int, ...], stride: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
        out = torch.empty_strided(shape, stride, dtype=dtype, device=device)
        return out.copy_(torch.rand(shape, generator=gen, dtype=dtype))

    prepared = [(c.op, [operand(*o) for o in c.operands], c.scalars) for c in calls]
    times = []
    for i in range(repeats + 2):
        t = time.perf_counter()
        for op, operands, scalars in prepared:
            op(*operands, **scalars)
        synchronize(device)
        if i >= 2:
            times.append((time.perf_counter() - t) * 1e3)
    return times
