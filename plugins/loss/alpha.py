"""Alpha loss: the rendered opacity (a render with white colours on black) against the foreground mask."""

from __future__ import annotations

import torch
from torch import Tensor

from framework.interfaces.loss import Loss
from framework.registry import register
from framework.types import FrameBatch, RenderOutput


@register("loss", "alpha")
class AlphaLoss(Loss):
    """The rendered opacity against the mask, under M_b (on by default: it ignores the band where mask errors live).

    norm "l1" (ours): mean over pixels of M_b |alpha - mask|. L1 suits a binary target: its gradient does not fade as
      the opacity approaches 0 or 1.
    norm "l2" (the paper's eq. 7, an L2 norm): per image || M_b (alpha - mask) ||_2 / sqrt(H W), i.e. the norm over
      the image divided by the norm of an all-ones image, so the paper's weight (10) means the same at every
      resolution; averaged over the batch. Its gradient, (M_b d) / (H W ||M_b d||_2 / sqrt(H W)), has the same
      size whatever the size of the error, like L1's, but points along the whole error image.
    """

    NORMS = ("l1", "l2")

    def __init__(self, boundary: bool = True, norm: str = "l1") -> None:
        super().__init__()
        if norm not in self.NORMS:
            raise ValueError(f"loss 'alpha': norm must be one of {self.NORMS}, got '{norm}'.")
        self.boundary = boundary
        self.norm = norm

    def forward(self, render: RenderOutput, batch: FrameBatch, aux: dict[str, Tensor]) -> Tensor:
        diff = render.alpha[..., 0] - batch.mask.to(render.alpha.dtype)  # [B, H, W]
        if self.boundary:
            diff = diff * batch.boundary.to(diff.dtype)
        if self.norm == "l1":
            return diff.abs().mean()
        mean_square = diff.square().flatten(1).mean(1)  # [B]
        # sqrt has an infinite slope at 0: a perfect image contributes 0 with a zero (not NaN) gradient
        safe = torch.where(mean_square > 0, mean_square, torch.ones_like(mean_square))
        return torch.where(mean_square > 0, safe.sqrt(), torch.zeros_like(mean_square)).mean()
