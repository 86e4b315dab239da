"""Blend-weight smoothness: the deformer reports the std of blend weights over the six points x +- s_l a_l."""

from __future__ import annotations

from torch import Tensor

from framework.interfaces.loss import Loss
from framework.registry import register
from framework.types import FrameBatch, RenderOutput


@register("loss", "weight_std")
class WeightStdLoss(Loss):
    """mean of aux["weight_std"]; zero when the deformer reports none (e.g. plain LBS with baked weights)."""

    aux_keys = ("weight_std",)

    def forward(self, render: RenderOutput, batch: FrameBatch, aux: dict[str, Tensor]) -> Tensor:
        std = (aux or {}).get("weight_std")
        if std is None or std.numel() == 0:
            return render.rgb.new_zeros(())
        return std.mean()
