"""Image quality metrics used by evaluation."""

from __future__ import annotations

from abc import ABC, abstractmethod

from torch import Tensor


class Metric(ABC):
    registry_name: str = ""
    higher_is_better: bool = True

    @abstractmethod
    def __call__(self, pred: Tensor, target: Tensor) -> Tensor:
        """pred, target: [B, H, W, 3] in [0, 1] -> [B] per-image values."""
