"""Blend-weight smoothness: the deformer reports the std of blend weights over the six points x +- s_l a_l."""

from __future__ import annotations

from torch import Tensor

from framework.interfaces.loss import Loss
from framework.registry import register
from framework.types import FrameBatch, RenderOutput


@register("loss", "weight_std")
class WeightStdLoss(Loss):
    """L_w (the paper's eq. 8) from aux["weight_std"] [N], one value per Gaussian; zero when the deformer reports none
    (e.g. plain LBS with baked weights).

    Eq. 8 writes a sum over Gaussians (Sum_i). `reduction` "mean" (paper_full's reading): the mean over Gaussians, so
    the paper's weight (0.2) means the same at 8k Gaussians as at 300k and as densification changes N; "sum": the
    sum as written, whose size (and so the weight's meaning) grows with the number of Gaussians.
    """

    aux_keys = ("weight_std",)
    REDUCTIONS = ("mean", "sum")

    def __init__(self, reduction: str = "mean") -> None:
        super().__init__()
        if reduction not in self.REDUCTIONS:
            raise ValueError(f"loss 'weight_std': reduction must be one of {self.REDUCTIONS}, got '{reduction}'.")
        self.reduction = reduction

    def forward(self, render: RenderOutput, batch: FrameBatch, aux: dict[str, Tensor]) -> Tensor:
        std = (aux or {}).get("weight_std")
        if std is None or std.numel() == 0:
            return render.rgb.new_zeros(())
        return std.mean() if self.reduction == "mean" else std.sum()
