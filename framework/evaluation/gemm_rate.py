"""The best matrix-product rate this machine reaches: the denominator of the arithmetic lower bounds that
`tools/bench_train.py` (the training step) and `tools/bench_render.py` (the novel-pose frame) print.

A square float32 product is the shape BLAS runs most efficiently; the MLPs' skinny products run slower. So an MLP's
FLOPs divided by this rate is a time no implementation on this hardware's BLAS goes below. Machines differ 2-3x, so a
bound is only read against times measured in the same run.
"""

from __future__ import annotations

import time

import torch

from framework.model.frame_timing import synchronize


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
