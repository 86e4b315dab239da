"""Faults injected on purpose into a training subprocess (SPLATRIG_PLUGINS=faults, PYTHONPATH=tests/helpers).

- loss `fault`: zero, except at training step `at_step` (its own call count, from 0), where `kind` = "nan_loss"
  returns NaN and "nan_grad" returns 0 whose gradient into the rendered image is NaN.
- loss `thread_probe` (zero): appends the CPU threads torch may use to the file `log`, one line per moment of the
  step: "loss N" in its forward, "backward N" in its backward, "optimizer N" before each optimizer step.
- SPLATRIG_TEST_STALL_CHECKPOINT_AT=<step> (with SPLATRIG_TEST_STALL_MARKER=<file>): the checkpoint save of that
  step stalls inside torch.save (its temporary file already open), after touching the marker file, so a test can
  kill the process in mid-write.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import torch
from torch import Tensor
from torch.optim.optimizer import register_optimizer_step_pre_hook

from framework.interfaces.loss import Loss
from framework.registry import register
from framework.types import FrameBatch, RenderOutput


class _NaNGradient(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: Tensor) -> Tensor:  # type: ignore[override]
        ctx.shape = x.shape
        return x.new_zeros(())

    @staticmethod
    def backward(ctx, grad: Tensor) -> Tensor:  # type: ignore[override]
        return grad.new_full(ctx.shape, float("nan"))


@register("loss", "fault")
class FaultLoss(Loss):
    def __init__(self, at_step: int, kind: str = "nan_loss") -> None:
        super().__init__()
        self.at_step, self.kind, self.calls = int(at_step), kind, 0

    def forward(self, render: RenderOutput, batch: FrameBatch, aux: dict[str, Tensor]) -> Tensor:
        step, self.calls = self.calls, self.calls + 1
        if step != self.at_step:
            return render.rgb.new_zeros(())
        if self.kind == "nan_loss":
            return render.rgb.new_full((), float("nan"))
        return _NaNGradient.apply(render.rgb)


def _log_threads(path: str, moment: str) -> None:
    with open(path, "a") as fh:
        fh.write(f"{moment} {torch.get_num_threads()}\n")


class _ThreadsInBackward(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: Tensor, path: str) -> Tensor:  # type: ignore[override]
        ctx.shape, ctx.path = x.shape, path
        return x.new_zeros(())

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None]:  # type: ignore[override]
        _log_threads(ctx.path, "backward")
        return grad.new_zeros(ctx.shape), None


@register("loss", "thread_probe")
class ThreadProbeLoss(Loss):
    def __init__(self, log: str) -> None:
        super().__init__()
        self.log = str(log)
        register_optimizer_step_pre_hook(lambda *_: _log_threads(self.log, "optimizer"))

    def forward(self, render: RenderOutput, batch: FrameBatch, aux: dict[str, Tensor]) -> Tensor:
        _log_threads(self.log, "loss")
        return _ThreadsInBackward.apply(render.rgb, self.log)


class _StallWhilePickled:
    """Pickled inside torch.save, i.e. after the checkpoint's temporary file was opened: marks the stall and sleeps."""

    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self):
        Path(self.marker).touch()
        time.sleep(3600)
        return (str, ("",))


def _stall_checkpoint_writes(at_step: int, marker: str) -> None:
    from framework.lightning.module import SplatModule

    original = SplatModule.on_save_checkpoint

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        original(self, checkpoint)
        if checkpoint.get("global_step") == at_step:
            checkpoint["stall"] = _StallWhilePickled(marker)

    SplatModule.on_save_checkpoint = on_save_checkpoint


if os.environ.get("SPLATRIG_TEST_STALL_CHECKPOINT_AT"):
    _stall_checkpoint_writes(
        int(os.environ["SPLATRIG_TEST_STALL_CHECKPOINT_AT"]), os.environ["SPLATRIG_TEST_STALL_MARKER"]
    )
