"""No densification: the Gaussian count stays as initialised (fixed-budget runs, tests, ablations)."""

from __future__ import annotations

from typing import Any

from framework.interfaces.densifier import Densifier
from framework.registry import register


@register("densifier", "none")
class NoDensifier(Densifier):
    def initialize_state(self, scene_scale: float = 1.0) -> dict[str, Any]:
        return {"scene_scale": float(scene_scale)}

    def step_post_backward(self, params, optimizers, state, step, info) -> None:
        return None
