"""How components execute: plain torch, or the compiled CPU kernels of `framework.kernels` where they apply.

Why an object and not a switch: whether a CPU run takes the compiled kernels (and the torch forms that suit a CPU) or
the code an accelerator runs is a choice about the whole model, made once when it is built (the `execution:` config
node, resolved against the device) and handed to every component with two forms. A component asks its `execution`
before it leaves torch; nothing reads a module-level setting, so two models in one process may run differently (a
tool times a GPU's code on a CPU beside the CPU's own).

`kernels` is "compiled" (the kernels take CPU float32/float64 tensors, which they read as numpy views; everything else
runs torch: on a GPU that is the same as "torch") or "torch" (torch everywhere, in the few-kernel forms an accelerator
takes, so a CPU runs a GPU's code operator for operator). The config's "auto" resolves to "compiled" on a CPU and to
"torch" elsewhere.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

KERNEL_CHOICES = ("auto", "torch", "compiled")


@dataclass(frozen=True)
class Execution:
    """How a model's components run; frozen, so every holder sees the choice it was built with."""

    kernels: str = "compiled"  # "compiled" | "torch" (resolved: never "auto")

    def __post_init__(self) -> None:
        if self.kernels not in ("torch", "compiled"):
            raise ValueError(
                f"execution.kernels: expected one of {KERNEL_CHOICES} (auto is resolved against the device), "
                f"got '{self.kernels}'."
            )

    @classmethod
    def resolve(cls, kernels: str, device: torch.device | str) -> Execution:
        """The execution a config's `kernels` asks for on `device`: auto is compiled on a CPU, torch elsewhere."""
        if kernels not in KERNEL_CHOICES:
            raise ValueError(f"execution.kernels: expected one of {KERNEL_CHOICES}, got '{kernels}'.")
        if kernels == "auto":
            kernels = "compiled" if torch.device(device).type == "cpu" else "torch"
        return cls(kernels)

    def compiled(self, *tensors: Tensor) -> bool:
        """Whether the compiled kernels take these tensors: kernels compiled, every tensor a CPU float32 or float64
        one (the kernels read them as numpy views, no copy, no cast)."""
        return self.kernels == "compiled" and all(
            t.device.type == "cpu" and t.dtype in (torch.float32, torch.float64) for t in tensors
        )


#: torch everywhere, in an accelerator's forms (a GPU's code on a CPU too)
TORCH = Execution("torch")
#: the compiled kernels for CPU float tensors, torch for the rest: what `auto` gives on a CPU. The default of the
#: stateless math's `execution` arguments and of a component nobody handed one, so a CPU runs as it always has.
COMPILED = Execution("compiled")


class ExecutionMixin:
    """Declares `execution` on a component interface with a default: the engine hands a built component the model's
    choice through `set_execution`, and a component with a single form ignores it."""

    execution: Execution = COMPILED

    def set_execution(self, execution: Execution) -> None:
        """Run as `execution` says from now on (called once, when the model is put together)."""
        self.execution = execution
