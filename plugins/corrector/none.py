"""The `none` corrector: the average-appearance model (no pose-dependent residuals)."""

from __future__ import annotations

from torch import Tensor

from framework.interfaces.corrector import Corrector
from framework.registry import register
from framework.types import Gaussians


@register("corrector", "none")
class NoCorrector(Corrector):
    """Returns the canonical Gaussians unchanged; has no parameters."""

    def forward(self, gaussians: Gaussians, pose: Tensor | None = None) -> Gaussians:
        return gaussians
