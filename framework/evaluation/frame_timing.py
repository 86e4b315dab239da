"""Wall time of rendering frames, measured the same way everywhere (tools/bench_render.py, pruning reports).

Rules: `warmup` frames first (caches, lazy initialisation, kernel compilation), then the median of `repeats` frames,
each timed as a whole (the device synchronised before the clock stops on CUDA).
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable

import torch


def synchronize(device: str | torch.device) -> None:
    if str(device).startswith("cuda"):
        torch.cuda.synchronize()


def time_frames(fn: Callable[[int], object], warmup: int, repeats: int, device: str | torch.device) -> float:
    """Median seconds of `fn(i)` over `repeats` calls after `warmup` calls (i counts every call)."""
    for i in range(warmup):
        fn(i)
    synchronize(device)
    times = []
    for i in range(repeats):
        t = time.perf_counter()
        fn(warmup + i)
        synchronize(device)
        times.append(time.perf_counter() - t)
    return statistics.median(times)
