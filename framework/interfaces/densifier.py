"""Densification strategies, with the protocol of gsplat's `Strategy`.

`params` maps names (means, quats, log_scales, opacity_logits, sh, latents, skin_weights...) to the canonical
`nn.Parameter`s; `optimizers` maps the same names to their optimizers, whose state must follow every change of N.
`info` carries what the renderer produced: "means2d" (its .grad), "radii", "width", "height", "n_cameras".
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any

import torch
from torch import nn

from framework.execution import ExecutionMixin


class Densifier(ExecutionMixin, ABC):
    registry_name: str = ""

    @abstractmethod
    def initialize_state(self, scene_scale: float = 1.0) -> dict[str, Any]: ...

    def step_pre_backward(  # noqa: B027 - optional hook
        self,
        params: dict[str, nn.Parameter],
        optimizers: dict[str, torch.optim.Optimizer],
        state: dict[str, Any],
        step: int,
        info: dict[str, Any],
    ) -> None:
        """Retain gradients the post-backward step needs."""

    def restart_schedule(self, state: dict[str, Any], step: int) -> None:  # noqa: B027 - optional hook
        """Stage 2 begins at `step`: a schedule that counts from the stage start (opacity resets) restarts here."""

    @abstractmethod
    def step_post_backward(
        self,
        params: dict[str, nn.Parameter],
        optimizers: dict[str, torch.optim.Optimizer],
        state: dict[str, Any],
        step: int,
        info: dict[str, Any],
    ) -> None: ...
