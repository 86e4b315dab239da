"""Divergence checks a GPU does not wait for: the step's finiteness probe skips a bad update on the device, and the
host reads the probe once the device has got there.

Why: the probe of `framework.lightning.divergence` is read on the host before every update, so that a bad step never
reaches the weights. On a GPU that read waits for the whole step's queue, after which the device idles while the host
issues the next step. Fused Adam can instead take the probe's verdict as a device tensor (`found_inf`, the mechanism of
mixed-precision loss scaling): it leaves parameters, moments and step count untouched where it is 1. The host then
reads the verdict from pinned memory when an event says the device has finished that step, usually while the next one
runs, and stops or rolls back exactly as before, naming the same step, terms and groups (from the probe's per-tensor
parts, kept on the device). Before a step that writes a checkpoint every pending verdict is read, waiting if need be,
so a checkpoint still never follows an unread bad step.

What a deferred verdict changes: the densifier's bookkeeping of a bad step runs with its non-finite gradients, and the
steps until the verdict is read run on; both are undone by the rollback (which reloads the checkpoint) or end with the
stop. On a CPU the read costs nothing, so training reads every probe at once there (`divergence.deferred: auto`).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass

import torch
from torch import Tensor

from framework.lightning.divergence import describe, finite_parts
from framework.lightning.host_copy import HostCopy


@dataclass
class _Verdict:
    step: int
    bad: HostCopy  # of the [] bool verdict
    parts: Tensor  # [T] the probe's per-tensor values, on the device (read only when bad)
    labels: list[tuple[str, str]]  # (kind, group name) per part; kind "total", "param" or "grad"
    total: Tensor  # [] the weighted loss
    terms: dict[str, Tensor]  # each [] loss term


def defers(optimizer: torch.optim.Optimizer) -> bool:
    """Whether `optimizer` can skip an update on the device: a torch Adam whose every group runs fused."""
    return isinstance(optimizer, torch.optim.Adam) and all(g.get("fused") for g in optimizer.param_groups)


class DeferredChecks:
    """The verdicts of the probes not read yet, oldest first."""

    def __init__(self) -> None:
        self._pending: deque[_Verdict] = deque()

    def __len__(self) -> int:
        return len(self._pending)

    def probe(self, step: int, total: Tensor, terms: Mapping[str, Tensor], optimizer: torch.optim.Optimizer) -> Tensor:
        """Probe the loss, every gradient and every parameter of this step (before the update) without a host read;
        returns the optimizer's `found_inf`: [] float32 on the parameters' device, 1 when the update must be skipped."""
        tensors, labels = [total.detach()], [("total", "")]
        for group in optimizer.param_groups:
            name = str(group.get("name", "?"))
            for p in group["params"]:
                if p.numel():
                    tensors.append(p)
                    labels.append(("param", name))
                    if p.grad is not None:
                        tensors.append(p.grad)
                        labels.append(("grad", name))
        parts = finite_parts(tensors)  # [T]
        bad = ~torch.isfinite(parts.sum())  # []
        self._pending.append(
            _Verdict(step, HostCopy([bad]), parts, labels, total.detach(), {k: v.detach() for k, v in terms.items()})
        )
        return bad.float()

    def first_bad(self, *, before_step: int | None = None) -> str | None:
        """Read the verdicts in order and return the message of the first bad one (forgetting every other pending
        verdict: they describe steps that the stop or the rollback discards), or None.

        before_step=None reads every pending verdict, waiting for the device where it has not finished; otherwise only
        those of steps before `before_step` whose device work is done, without waiting."""
        while self._pending:
            verdict = self._pending[0]
            if before_step is not None and (verdict.step >= before_step or not verdict.bad.ready()):
                return None
            verdict.bad.wait()
            self._pending.popleft()
            if bool(verdict.bad.values()[0].numpy()):
                self._pending.clear()
                return _message(verdict)
        return None

    def clear(self) -> None:
        self._pending.clear()


def _message(verdict: _Verdict) -> str:
    """`diagnose`'s sentence for a deferred verdict, from the per-tensor parts the probe kept."""
    finite = torch.isfinite(verdict.parts).tolist()
    bad_params: list[str] = []
    bad_grads: list[str] = []
    for ok, (kind, group) in zip(finite, verdict.labels, strict=True):
        names = bad_params if kind == "param" else bad_grads if kind == "grad" else None
        if not ok and names is not None and group not in names:
            names.append(group)
    return describe(verdict.step, verdict.total, verdict.terms, bad_params, bad_grads)
