"""Alpha loss L_alpha (the paper's eq. 7): the rendered opacity (white colours on black) against the foreground mask,
under the boundary mask M_b."""

from __future__ import annotations

import torch
from torch import Tensor

from framework.interfaces.loss import Loss
from framework.registry import register
from framework.types import FrameBatch, RenderOutput


@register("loss", "alpha")
class AlphaLoss(Loss):
    """The rendered opacity against the mask, under M_b (`boundary`, on by default: eq. 7 has M_b inside the norm, so
    the band where mask errors live costs nothing).

    Eq. 7 writes an L2 norm, || M_b (alpha - M) ||_2, and leaves open whether it is squared and how it is normalised:
    norm "mse" (paper_full's reading): mean over pixels of (M_b (alpha - M))^2, the squared norm per pixel. It is the
      usual "L2 loss" of the 3DGS family, does not depend on the resolution, and its gradient fades as the error does,
      so the paper's weight (10) weighs it against the L1 term (0.8) pixel for pixel.
    norm "rms": per image || M_b (alpha - M) ||_2 / sqrt(H W) (the norm, divided by that of an all-ones image so it does
      not grow with the resolution), averaged over the batch. Its gradient has the same size whatever the size of
      the error, so at weight 10 it keeps pushing as hard on a nearly right silhouette as on a wrong one.
    norm "l1" (the project's earlier form): mean over pixels of M_b |alpha - M|.
    """

    NORMS = ("mse", "rms", "l1")

    def __init__(self, boundary: bool = True, norm: str = "mse") -> None:
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
        if self.norm == "mse":
            return diff.square().mean()
        mean_square = diff.square().flatten(1).mean(1)  # [B]
        # sqrt has an infinite slope at 0: a perfect image contributes 0 with a zero (not NaN) gradient
        safe = torch.where(mean_square > 0, mean_square, torch.ones_like(mean_square))
        return torch.where(mean_square > 0, safe.sqrt(), torch.zeros_like(mean_square)).mean()
