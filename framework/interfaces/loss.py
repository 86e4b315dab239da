"""Loss terms. Each returns an unweighted scalar; weights come from the config and every term is logged."""

from __future__ import annotations

from abc import ABC, abstractmethod

from torch import Tensor, nn

from framework.execution import ExecutionMixin
from framework.types import FrameBatch, RenderOutput


class Loss(nn.Module, ExecutionMixin, ABC):
    registry_name: str = ""
    #: deformer aux outputs this term reads (e.g. "weight_std"); a deformer computes only those some term reads
    aux_keys: tuple[str, ...] = ()

    @abstractmethod
    def forward(self, render: RenderOutput, batch: FrameBatch, aux: dict[str, Tensor]) -> Tensor:
        """render rgb/alpha are [B, H, W, ...] matching batch.image; aux comes from the deformer."""
