"""D-SSIM = 1 - SSIM (3DGS's, which the paper uses) or (1 - SSIM) / 2, with kornia's Gaussian-window SSIM (window 11,
sigma 1.5), moments filtered in one call."""

from __future__ import annotations

from torch import Tensor

from framework.image.ssim import ssim_map
from framework.interfaces.loss import Loss
from framework.registry import register
from framework.types import FrameBatch, RenderOutput


def to_nchw(x: Tensor) -> Tensor:
    return x.permute(0, 3, 1, 2)  # [B, H, W, C] -> [B, C, H, W]


@register("loss", "dssim")
class DSSIMLoss(Loss):
    """Structural dissimilarity over the whole image, mean over pixels, channels and the batch.

    `form` "full" (paper_full): 1 - SSIM. The paper takes D-SSIM "the same as that in 3DGS", whose code computes
    1 - SSIM, so the paper's weight (0.2) applies to that. "half": (1 - SSIM) / 2 (the project's earlier form, in
    [0, 1] like the L1 term; at the same weight it halves the term).

    'same' padding (reflected borders) keeps border pixels in the loss, as 3DGS training does. Images smaller than
    the window use the largest window the reflection allows (down to one pixel).

    `foreground_only` (the paper's "only foreground" row) compares the two images with everything outside the human
    mask set to zero in both, so nothing rendered outside the mask changes the loss (SSIM of two zero patches is 1).

    `compiled` (default) computes the SSIM map, forward and backward, with the compiled loops of
    `framework.kernels.ssim` where the execution compiles the images (CPU float); false keeps kornia's filter and
    torch (the same values to rounding; a benchmark switch).
    """

    FORMS = {"full": 1.0, "half": 0.5}

    def __init__(
        self, window_size: int = 11, foreground_only: bool = False, compiled: bool = True, form: str = "full"
    ) -> None:
        super().__init__()
        if window_size < 1 or window_size % 2 == 0:
            raise ValueError(f"loss 'dssim': window_size must be a positive odd number, got {window_size}.")
        if form not in self.FORMS:
            raise ValueError(f"loss 'dssim': form must be one of {tuple(self.FORMS)}, got '{form}'.")
        self.form = form
        self.window_size = window_size
        self.foreground_only = foreground_only
        self.compiled = compiled

    def forward(self, render: RenderOutput, batch: FrameBatch, aux: dict[str, Tensor]) -> Tensor:
        pred, target = to_nchw(render.rgb), to_nchw(batch.image.to(render.rgb.dtype))
        if self.foreground_only:
            keep = batch.mask.to(pred.dtype).unsqueeze(1)  # [B, 1, H, W]
            pred, target = pred * keep, target * keep
        # Reflected borders need the half window below the image size: tiny renders get a smaller window.
        window = min(self.window_size, 2 * min(pred.shape[-2:]) - 1)
        if self.compiled and self.execution.compiled(pred):
            from framework.kernels.ssim import ssim_map as compiled_ssim_map  # imports numba: first use only

            ssim = compiled_ssim_map(pred, target, window)  # [B, 3, H, W]
        else:
            ssim = ssim_map(pred, target, window)  # [B, 3, H, W]
        return (1.0 - ssim).mean() * self.FORMS[self.form]
