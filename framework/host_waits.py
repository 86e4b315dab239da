"""Which operators make a GPU's host wait, and a dispatch mode that counts them with every operator issued.

Why: a GPU step or frame costs the host time to issue each operator (a kernel launch or at least a dispatch), and
every operator whose result the host needs (`.item()`, a boolean index, `nonzero`, a tensor made from Python values,
a copy from host memory without `non_blocking`) waits until the device has run everything queued. Both can be
counted on any machine by running the GPU's code path on a CPU (`framework.runtime.use_compiled_paths(False)`):
`tools/count_syncs.py` counts a training step, `tools/bench_render.py` a novel-pose frame, with the rules here.
"""

from __future__ import annotations

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


class OperatorCount(TorchDispatchMode):
    """Counts every aten operator (`operators`) and the host waits among them (`waits`) while active."""

    def __init__(self) -> None:
        super().__init__()
        self.operators = 0
        self.waits = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        self.operators += 1
        self.waits += wait_kind(func, args, kwargs) is not None
        return func(*args, **kwargs)
