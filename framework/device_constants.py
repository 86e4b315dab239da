"""Constant tensors on the device and dtype where they are used, copied there once instead of in every call.

Why: on a GPU, `.to(device)` of a tensor kept in host memory, and `torch.tensor([...], device=...)`, copy from
ordinary (pageable) host memory, and such a copy waits until every kernel queued before it has run: the host stops
running ahead of the device, once per copy. A training step made about ten such copies of constants (index tables,
an identity quaternion, the forward kinematics' ancestor tables, the SSIM window) before they went through here.
`tools/count_syncs.py` counts the `torch.tensor([...])` kind on any machine; `.to(device)` of a CPU constant is a
no-op on a CPU, so only a GPU (`torch.cuda.set_sync_debug_mode("warn")`) shows that kind.
"""

from __future__ import annotations

import functools

import torch
from torch import Tensor

#: (id of the constant, device, dtype) -> (the constant, its copy); the constant is kept so its id cannot be reused
_copies: dict[tuple[int, torch.device, torch.dtype], tuple[Tensor, Tensor]] = {}


def constant_on(constant: Tensor, device: torch.device | str, dtype: torch.dtype | None = None) -> Tensor:
    """`constant` (a module-level tensor that never changes) on `device` in `dtype` (default its own), copied on the
    first request and reused after: never write to the result."""
    device, dtype = torch.device(device), dtype or constant.dtype
    if constant.device == device and constant.dtype == dtype:
        return constant
    key = (id(constant), device, dtype)
    hit = _copies.get(key)
    if hit is None or hit[0] is not constant:
        hit = _copies[key] = (constant, constant.to(device=device, dtype=dtype))
    return hit[1]


@functools.lru_cache(maxsize=256)
def values_on(values: tuple[float, ...], device: torch.device, dtype: torch.dtype = torch.long) -> Tensor:
    """A tensor of these Python numbers on `device` (an index by default), made once per (values, device, dtype):
    never write to the result."""
    return torch.tensor(values, dtype=dtype, device=device)
