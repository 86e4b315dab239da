"""L1 image loss, optionally under the boundary mask M_b and/or restricted to the foreground."""

from __future__ import annotations

from torch import Tensor

from framework.interfaces.loss import Loss
from framework.registry import register
from framework.types import FrameBatch, RenderOutput


def pixel_weights(batch: FrameBatch, boundary: bool, foreground_only: bool) -> Tensor | None:
    """[B, H, W] per-pixel weights (M_b and/or the mask), or None for a plain mean."""
    w = None
    if boundary:
        w = batch.boundary
    if foreground_only:
        w = batch.mask if w is None else w * batch.mask
    return w


@register("loss", "l1")
class L1Loss(Loss):
    """mean over pixels and channels of w * |rgb - image|.

    The mean runs over every pixel (zero-weighted ones included) rather than over the weighted area, so the term's
    scale stays that of a plain L1 and the paper's weight (0.8) means the same with and without the mask. M_b is 0 in
    a band around the silhouette, where mask and pose errors make the ground truth unreliable.
    """

    def __init__(self, boundary: bool = True, foreground_only: bool = False) -> None:
        super().__init__()
        self.boundary = boundary
        self.foreground_only = foreground_only

    def forward(self, render: RenderOutput, batch: FrameBatch, aux: dict[str, Tensor]) -> Tensor:
        err = (render.rgb - batch.image).abs()  # [B, H, W, 3]
        w = pixel_weights(batch, self.boundary, self.foreground_only)
        if w is not None:
            err = err * w.unsqueeze(-1).to(err.dtype)
        return err.mean()
