"""Tensor values for the host without waiting for the device: a copy into pinned memory, queued behind the work that
makes the values, and an event that says when it has landed.

Why: reading a GPU tensor on the host (`float(t)`, `.item()`) waits until the device has run everything queued before
it, and then the device idles while the host issues the next kernels. Values the host only reports or checks later
(the divergence probe's verdict, the progress bar's loss and PSNR) can instead be read once `ready()`, usually a step
later. On a CPU the copy is the tensor itself and is ready at once.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor


class HostCopy:
    """Host copies of `tensors`, made without a wait; read them with `values()` once `ready()` or after `wait()`."""

    def __init__(self, tensors: Sequence[Tensor]) -> None:
        # a non_blocking copy from CUDA lands in pinned memory, in the order of the current stream
        self._values = [t.detach().to("cpu", non_blocking=True) for t in tensors]
        self._done: torch.cuda.Event | None = None
        if any(t.is_cuda for t in tensors):
            self._done = torch.cuda.Event()
            self._done.record()

    def ready(self) -> bool:
        """Whether the copies have landed (never waits)."""
        return self._done is None or self._done.query()

    def wait(self) -> None:
        """Wait until the copies have landed."""
        if self._done is not None:
            self._done.synchronize()

    def values(self) -> list[Tensor]:
        """The host tensors; valid once `ready()` or after `wait()`. Read them with `.numpy()`: host memory, no
        operator that a sync counter would take for a device read."""
        return self._values
