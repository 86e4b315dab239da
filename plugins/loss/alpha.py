"""Alpha loss: the rendered opacity (a render with white colours on black) against the foreground mask."""

from __future__ import annotations

from torch import Tensor

from framework.interfaces.loss import Loss
from framework.registry import register
from framework.types import FrameBatch, RenderOutput


@register("loss", "alpha")
class AlphaLoss(Loss):
    """mean over pixels of M_b * |alpha - mask| (L1 by default; `norm: l2` squares the error).

    The paper writes this term next to its L1 image term without a square, so we read it as L1, and L1 suits a
    binary target: its gradient does not fade as the opacity approaches 0 or 1, so it removes the faint haze around
    the silhouette that an L2 leaves. M_b (on by default) ignores the band where mask errors live.
    """

    def __init__(self, boundary: bool = True, norm: str = "l1") -> None:
        super().__init__()
        if norm not in ("l1", "l2"):
            raise ValueError(f"loss 'alpha': norm must be 'l1' or 'l2', got '{norm}'.")
        self.boundary = boundary
        self.norm = norm

    def forward(self, render: RenderOutput, batch: FrameBatch, aux: dict[str, Tensor]) -> Tensor:
        diff = render.alpha[..., 0] - batch.mask.to(render.alpha.dtype)  # [B, H, W]
        err = diff.abs() if self.norm == "l1" else diff.square()
        if self.boundary:
            err = err * batch.boundary.to(err.dtype)
        return err.mean()
