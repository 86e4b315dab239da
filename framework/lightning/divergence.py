"""A training that goes wrong says so: a NaN or Inf in the loss, a gradient or a parameter is named with its step.

Per step the module folds the total loss, every parameter group's gradient and every parameter (the values this
step's forward used) into ONE scalar (`finite_probe`: a sum of sums, non-finite exactly when some entry is NaN or
Inf, or the sum overflows) and reads it once on the host, before the optimizer step, so a bad step never reaches
the weights. On a GPU (`divergence.deferred`) the optimizer skips a bad update on the device instead and the host
reads the scalar when the device has finished the step (`framework.lightning.deferred_checks`). On steps that write
a checkpoint the parameters are probed once more after the update (optimizer and densifier), so a checkpoint never
stores non-finite values. Only when a probe is non-finite does the slow path (`diagnose`) look at every term and
group to name them.

What happens then is `divergence.action` (conf/train.yaml):
- `stop` (default): raise `TrainingDiverged` with one message naming the step, the loss terms and the parameter
  groups; the checkpoints on disk are those of the last good step (no checkpoint is written after a bad one).
- `rollback`: reload the last good checkpoint (`last.ckpt`: parameters, optimizer and densifier state, stage), multiply
  every learning rate by `lr_factor`, print the same message once, and go on; the step counter keeps counting (the
  steps since that checkpoint are lost, not replayed). After `max_rollbacks` rollbacks it stops as `stop` does.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import torch
from torch import Tensor

from framework.config_schema import Divergence
from framework.errors import SplatrigError

ACTIONS = ("stop", "rollback")


class TrainingDiverged(SplatrigError):
    """NaN or Inf in the loss, a gradient or a parameter (the message names the step, the terms and the groups)."""


@dataclass(frozen=True)
class DivergencePolicy:
    action: str
    lr_factor: float
    max_rollbacks: int
    deferred: bool | str  # read the probe after the step (framework.lightning.deferred_checks); auto: on a GPU

    @classmethod
    def from_config(cls, node: Divergence) -> DivergencePolicy:
        """From the typed `divergence` config node (its defaults: framework.config_schema.Divergence); bad values
        raise ValueError naming the key."""
        policy = cls(
            action=node.action, lr_factor=node.lr_factor, max_rollbacks=node.max_rollbacks, deferred=node.deferred
        )
        if not (isinstance(policy.deferred, bool) or policy.deferred == "auto"):
            raise ValueError(f"divergence.deferred: expected true, false or auto, found '{policy.deferred}'.")
        if policy.action not in ACTIONS:
            raise ValueError(f"divergence.action: expected one of {ACTIONS}, found '{policy.action}'.")
        if not 0.0 < policy.lr_factor < 1.0:
            raise ValueError(f"divergence.lr_factor: expected a number in (0, 1), found {policy.lr_factor}.")
        if policy.max_rollbacks < 0:
            raise ValueError(f"divergence.max_rollbacks: expected >= 0, found {policy.max_rollbacks}.")
        return policy


@torch.no_grad()  # no graph, and no detach per tensor (~45 operators a step that a GPU's host would issue)
def finite_parts(tensors: list[Tensor]) -> Tensor:
    """One value per tensor [T], finite iff the tensor is (unless its sum overflows float32: entries around 1e32, a
    divergence of its own). Sums in the tensors' dtype: several times faster than float64 sums on a CPU. Every tensor
    must hold at least one value."""
    present = list(tensors)
    if all(t.is_cuda and t.dtype == torch.float32 for t in present):
        # one multi-tensor kernel for all of them instead of two kernels per tensor (a step probes ~45 tensors);
        # the 1-norm is non-finite exactly when the sum of the tensor's absolute values is
        return torch.stack(torch._foreach_norm(present, 1.0))
    return torch.stack([t.sum().float() for t in present])


def finite_probe(tensors: Iterable[Tensor | None]) -> Tensor:
    """One scalar that is finite iff every given tensor is (None and empty entries are skipped); see `finite_parts`."""
    present = [t for t in tensors if t is not None and t.numel()]
    if not present:
        return torch.zeros(())
    return finite_parts(present).sum()


def grads_and_params(optimizer: torch.optim.Optimizer) -> tuple[list[Tensor | None], list[Tensor]]:
    """Every gradient and every parameter of the optimizer's groups."""
    params = [p for g in optimizer.param_groups for p in g["params"]]
    return [p.grad for p in params], params


def _nonfinite_groups(optimizer: torch.optim.Optimizer, attr: str) -> list[str]:
    out = []
    for group in optimizer.param_groups:
        tensors = [p if attr == "data" else p.grad for p in group["params"]]
        if any(t is not None and not bool(torch.isfinite(t).all()) for t in tensors):
            out.append(str(group.get("name", "?")))
    return out


def diagnose(step: int, total: Tensor, terms: Mapping[str, Tensor], optimizer: torch.optim.Optimizer) -> str:
    """One sentence naming what is non-finite at `step` (the slow path, run only after the probe failed)."""
    return describe(step, total, terms, _nonfinite_groups(optimizer, "data"), _nonfinite_groups(optimizer, "grad"))


def describe(step: int, total: Tensor, terms: Mapping[str, Tensor], bad_params: list[str], bad_grads: list[str]) -> str:
    """The sentence of `diagnose`, given the names of the parameter groups whose values or gradients are non-finite
    (found by reading the tensors now, or from a probe's per-tensor parts kept since the step)."""
    parts = []
    total_value, values = float(total.detach()), {k: float(v.detach()) for k, v in terms.items()}
    bad_terms = {k: v for k, v in values.items() if not math.isfinite(v)}
    if bad_terms:
        parts.append("loss term " + ", ".join(f"'{k}' = {v}" for k, v in bad_terms.items()))
    elif not math.isfinite(total_value):
        parts.append(f"the weighted total loss = {total_value} (every term finite: a weight or an overflow)")
    if bad_params:
        parts.append(
            "parameter values of group " + ", ".join(f"'{g}'" for g in bad_params) + " (from the previous "
            "step's optimizer or densifier update)"
        )
    if bad_grads:
        parts.append("gradient of parameter group " + ", ".join(f"'{g}'" for g in bad_grads))
    if not parts:
        parts.append("the sum of the loss, gradients and parameters overflowed (every entry is finite)")
    return f"training diverged at step {step}: non-finite " + "; ".join(parts)
