"""Which operators make a GPU's host wait or queue work on it, and a dispatch mode that counts them.

Why: a GPU step or frame costs the host time to issue each operator (a kernel launch or at least a dispatch), and
every operator whose result the host needs (`.item()`, a boolean index, `nonzero`, a tensor made from Python values,
a copy from host memory without `non_blocking`) waits until the device has run everything queued. Both can be
counted on any machine by running the GPU's code path on a CPU (the torch execution, `framework.execution.TORCH`):
`tools/count_syncs.py` counts a training step, `tools/bench_render.py` a novel-pose frame, with the rules here.

Not every operator queues device work: about a third of a training step's are views (`view`, `select`,
`unsqueeze`, `expand`, `t`, `detach`, ...), which only make a new tensor header on the host, and a few are bare
allocations (the caching allocator hands out memory without a kernel). `queues_device_work` tells them apart, so the
tools report both the operators (the host's dispatches) and those that queue a kernel or a copy (the launches). A
composite operator may still launch more than one kernel (a sort, a multi-tensor `_foreach_` over many chunks): the
launch count is a lower bound.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import torch
from torch.utils._python_dispatch import TorchDispatchMode

aten = torch.ops.aten

#: operators whose result the host needs (a value, or an output size that depends on the data)
SYNC_OPS = {
    aten._local_scalar_dense.default: "item / float / bool",
    aten.nonzero.default: "nonzero",
    aten.masked_select.default: "masked_select",
    aten.equal.default: "equal",
    aten.is_nonzero.default: "is_nonzero",
    aten._unique2.default: "unique",
    aten.unique_dim.default: "unique",
    aten.repeat_interleave.Tensor: "repeat_interleave",
    # a tensor made from Python values (`torch.tensor([...])`, `new_tensor`, `as_tensor` of a list): on a GPU it is
    # built on the host and copied over, and a copy from ordinary (pageable) memory waits for the queue to drain
    aten.lift_fresh.default: "tensor from Python values (host-to-device copy)",
}


#: operators that queue nothing on the device besides views: allocations the caching allocator serves from its pool,
#: and `_unsafe_view` (a reshape's result taking over its input's storage, no copy)
NO_DEVICE_WORK = {
    aten.empty.memory_format,
    aten.empty_strided.default,
    aten.empty_like.default,
    aten.new_empty.default,
    aten.new_empty_strided.default,
    aten._unsafe_view.default,
}


def _crosses_from_host(func, args, kwargs) -> bool:
    """Whether this operator copies a host tensor to another device without `non_blocking` (a `.to(device)` or
    `copy_` from the CPU): on a GPU, a copy from pageable memory that waits for the queue. Seen only where a second
    device exists (a GPU machine, or a test's meta device): on a CPU alone `.to("cpu")` is no operator at all."""
    if func is aten._to_copy.default:
        source, target = args[0], kwargs.get("device")
    elif func is aten.copy_.default:
        source, target = args[1], args[0].device
    else:
        return False
    if target is None or kwargs.get("non_blocking") or (len(args) > 2 and args[2] is True):
        return False
    return source.device.type == "cpu" and torch.device(target).type != "cpu"


def wait_kind(func, args, kwargs) -> str | None:
    """What kind of host wait this aten call is on a GPU, or None when it is none."""
    kind = SYNC_OPS.get(func)
    if func is aten.index.Tensor and any(
        isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in (args[1] if len(args) > 1 else []) or []
    ):
        kind = "boolean index"
    if func is aten.repeat_interleave.Tensor and kwargs.get("output_size") is not None:
        kind = None  # the output size is given: nothing to wait for
    if _crosses_from_host(func, args, kwargs):
        kind = "host-to-device copy (.to)"
    return kind


def queues_device_work(func, wait: str | None) -> bool:
    """Whether this aten call queues work on a GPU (a kernel or a copy), given its `wait_kind`: not a view (a new
    header on the host, `func.is_view`) nor a bare allocation. A host wait always does, as it copies a value across;
    that includes `lift_fresh`, which the schema calls a view but which marks a tensor made from Python values."""
    return wait is not None or not (func.is_view or func in NO_DEVICE_WORK)


class OperatorCount(TorchDispatchMode):
    """Counts every aten operator (`operators`), those that queue device work (`launches`) and the host waits among
    them (`waits`) while active."""

    def __init__(self) -> None:
        super().__init__()
        self.operators = 0
        self.launches = 0
        self.waits = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        wait = wait_kind(func, args, kwargs)
        self.operators += 1
        self.launches += queues_device_work(func, wait)
        self.waits += wait is not None
        return func(*args, **kwargs)


def cuda_device_events(fn: Callable[[], object]) -> int | None:
    """Kernels, copies and fills a CUDA device ran for one call of `fn`, as the profiler records them (CUPTI).

    Why: the dispatch-mode counters above see aten operators only, and under them `torch.compile` runs the functions
    it wraps eagerly, so they cannot count what compiled code launches (fused Triton kernels); the profiler records
    what the device itself ran, compiled or not. None without a CUDA device, or when the profiler recorded no device
    event (no CUPTI): never a zero that was not measured."""
    if not torch.cuda.is_available():
        return None
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile

    _start_cupti()
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        fn()
        torch.cuda.synchronize()
    count = sum(1 for event in prof.events() if event.device_type == DeviceType.CUDA)
    return count or None


@functools.cache
def _start_cupti() -> None:
    """A throwaway profiler session, once per process: the first one starts CUPTI, so no measured session is first."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]):
        torch.zeros(1, device="cuda")
        torch.cuda.synchronize()
