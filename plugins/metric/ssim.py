"""SSIM (Wang et al. 2004) with the standard Gaussian window: 11 taps, sigma 1.5, K1 0.01, K2 0.03."""

from __future__ import annotations

from torch import Tensor

from framework.interfaces.metric import Metric
from framework.registry import register
from framework.runtime import exact_float32

WINDOW = 11


@register("metric", "ssim")
class SSIM(Metric):
    """Mean SSIM per image over the 'valid' window positions and the three channels.

    Valid cropping (no padded borders) matches the reference implementations papers report (Wang's MATLAB code,
    scikit-image with gaussian_weights=True), so numbers are comparable with published tables.
    """

    higher_is_better = True

    def __call__(self, pred: Tensor, target: Tensor) -> Tensor:
        from kornia.metrics import ssim

        self.check_images(pred, target)
        if min(pred.shape[1], pred.shape[2]) < WINDOW:
            raise ValueError(
                f"metric 'ssim': images must be at least {WINDOW}x{WINDOW} pixels for the standard window, got "
                f"{pred.shape[1]}x{pred.shape[2]}."
            )
        p = pred.permute(0, 3, 1, 2).float()  # [B, 3, H, W]
        t = target.permute(0, 3, 1, 2).float()
        with exact_float32():  # a reported metric: the same number on a GPU as on a CPU (no TF32 convolutions)
            return ssim(p, t, WINDOW, max_val=1.0, padding="valid").mean(dim=(1, 2, 3))  # [B]
