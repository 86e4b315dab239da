"""Peak signal-to-noise ratio for images in [0, 1]."""

from __future__ import annotations

import torch
from torch import Tensor

from framework.guards import PSNR_MSE_FLOOR
from framework.interfaces.metric import Metric
from framework.registry import register


@register("metric", "psnr")
class PSNR(Metric):
    """10 log10(1 / MSE) per image over all pixels and channels (whole image, background included)."""

    higher_is_better = True

    def __call__(self, pred: Tensor, target: Tensor) -> Tensor:
        self.check_images(pred, target)
        mse = (pred.double() - target.double()).square().mean(dim=(1, 2, 3))  # [B], float64 for tiny errors
        return (-10.0 * torch.log10(mse.clamp_min(PSNR_MSE_FLOOR))).float()
