"""Peak signal-to-noise ratio for images in [0, 1]."""

from __future__ import annotations

import torch
from torch import Tensor

from framework.interfaces.metric import Metric
from framework.registry import register

MSE_FLOOR = 1e-10  # identical images score 100 dB instead of inf, so averages over frames stay finite


def _check_images(name: str, pred: Tensor, target: Tensor) -> None:
    if pred.shape != target.shape or pred.dim() != 4 or pred.shape[-1] != 3:
        raise ValueError(
            f"metric '{name}': expected pred and target of one shape [B, H, W, 3], got {tuple(pred.shape)} and "
            f"{tuple(target.shape)}."
        )


@register("metric", "psnr")
class PSNR(Metric):
    """10 log10(1 / MSE) per image over all pixels and channels (whole image, background included)."""

    higher_is_better = True

    def __call__(self, pred: Tensor, target: Tensor) -> Tensor:
        _check_images("psnr", pred, target)
        mse = (pred.double() - target.double()).square().mean(dim=(1, 2, 3))  # [B], float64 for tiny errors
        return (-10.0 * torch.log10(mse.clamp_min(MSE_FLOOR))).float()
