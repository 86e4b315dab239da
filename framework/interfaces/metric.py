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

    def check_images(self, pred: Tensor, target: Tensor) -> None:
        """Every metric takes the same input; one check gives every metric the same message."""
        if pred.shape != target.shape or pred.dim() != 4 or pred.shape[-1] != 3:
            raise ValueError(
                f"metric '{self.registry_name}': expected pred and target of one shape [B, H, W, 3], got "
                f"{tuple(pred.shape)} and {tuple(target.shape)}."
            )
