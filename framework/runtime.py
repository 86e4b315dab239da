"""Process settings: the allocator's reuse of freed tensor memory on a CPU, float32 arithmetic without TF32 on a GPU
where our numbers depend on it, the default device of a trained model, and torch's CPU threads for small work.
(Whether the compiled CPU kernels run is no process setting: `framework.execution` is chosen per model.)

(The OpenMP wait policy is the other one; it must be in the environment before torch is imported, so the entry point
sets it on its first lines.)
"""

from __future__ import annotations

import ctypes
import os
from collections.abc import Iterator
from contextlib import contextmanager

import torch

# glibc mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_MMAP_THRESHOLD = 32 * 2**20  # glibc's largest accepted value on 64-bit
_TRIM_THRESHOLD = 2**31 - 1


def reuse_freed_memory() -> bool:
    """Serve blocks up to 32 MB from the heap and never trim it (glibc), so a tensor freed in one training step is
    reused by the next instead of being unmapped and faulted in again page by page (fewer page faults, shorter steps:
    docs/results/speed.md). Peak memory is unchanged;
    the process keeps its high-water mark instead of returning it between steps.

    `SPLATRIG_MALLOC=system` in the environment keeps glibc's defaults. Returns whether the setting was applied
    (False off glibc)."""
    if os.environ.get("SPLATRIG_MALLOC", "").lower() == "system":
        return False
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD)) and bool(mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD))


@contextmanager
def exact_float32() -> Iterator[None]:
    """Within the block, float32 convolutions on a GPU round as float32, not TF32.

    Why: cuDNN takes float32 convolutions as TF32 by default (`torch.backends.cudnn.allow_tf32`), rounding every input
    to a 10-bit mantissa. SSIM subtracts squared means from filtered squares, which turns that rounding into an error
    of its own size: emulated on a CPU (tools/emulate_tf32.py), TF32 moved the mean SSIM of a 512^2 image pair by
    1.9e-2, float32 by 3e-6. The SSIM metric and D-SSIM loss and the LPIPS network run in this block. A CPU ignores
    the flag. Matrix products are TF32 only under `torch.set_float32_matmul_precision("high")`, which training keeps
    at "highest" (TF32 moved LBS translations by 1.5 mm in the same emulation); their flag is left alone here,
    because torch refuses to report the matmul precision once its legacy and new switches have both been set, and
    Lightning asks."""
    conv = torch.backends.cudnn.allow_tf32
    torch.backends.cudnn.allow_tf32 = False
    try:
        yield
    finally:
        torch.backends.cudnn.allow_tf32 = conv


def default_device() -> str:
    """Where a trained model renders when nobody says: the GPU when there is one, else the CPU."""
    return "cuda" if torch.cuda.is_available() else "cpu"


@contextmanager
def cpu_threads(threads: int | None, device: torch.device) -> Iterator[None]:
    """Within the block, torch's CPU operators use at most `threads` threads (None, or a device other than the CPU:
    no change).

    Why: the training entry point makes OpenMP's idle threads sleep (`OMP_WAIT_POLICY=PASSIVE`, so they do not starve
    the compiled loops' pool), and then every parallel operator pays for waking them. For the step's small work that
    costs more than the second thread gives (fused Adam over the CPU model's ~25 tensors is about twice as fast on one
    thread, and no faster on two at 16x the Gaussians). The training step runs its losses,
    optimizer, checks and densifier bookkeeping in this block (`small_work_threads`). Setting the count costs well
    under a microsecond, and element-wise results do not depend on it."""
    current = torch.get_num_threads()
    if threads is None or device.type != "cpu" or threads >= current:
        yield
        return
    torch.set_num_threads(max(1, int(threads)))
    try:
        yield
    finally:
        torch.set_num_threads(current)
