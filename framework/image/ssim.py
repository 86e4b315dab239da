"""SSIM map for the training loss: kornia's Gaussian-window SSIM with its five local moments filtered in one call.

`kornia.metrics.ssim` filters the two images, their squares and their product one after the other: ten depthwise
convolutions of three channels each, and as many in the backward. Here the five maps are stacked along the channels and
go through `kornia.filters.filter2d_separable` once (same kernel, same reflected borders, same combination), so the
training step pays for two convolutions of fifteen channels. The values equal kornia's (tested in float64, with
gradients), at about half the loss's forward time of the per-moment form (`tools/bench_train.py`). The compiled form of
the whole map, forward and backward, is `framework.kernels.ssim` (the same window, constants, borders and combination);
the D-SSIM loss chooses between them by its execution. Evaluation keeps `kornia.metrics.ssim`, whose no-gradient CPU
path is already channels-last.
"""

from __future__ import annotations

import functools

import torch
from torch import Tensor

SIGMA = 1.5
"""Standard deviation of the Gaussian window, in pixels (Wang et al. 2004; kornia's and 3DGS's choice)."""


@functools.lru_cache(maxsize=32)
def gaussian_window(window_size: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """kornia's Gaussian window [1, K], made once per size, dtype and device: built per call it is a tensor from Python
    values, on a GPU a host-to-device copy that waits for the queue (`framework.device_constants`)."""
    from kornia.filters.kernels import get_gaussian_kernel1d

    return get_gaussian_kernel1d(window_size, SIGMA, device=torch.device("cpu"), dtype=dtype).to(device)


def ssim_constants(max_val: float) -> tuple[float, float]:
    """(c1, c2) = ((0.01 L)^2, (0.03 L)^2) for the dynamic range L = max_val (Wang et al. 2004, kornia)."""
    return (0.01 * max_val) ** 2, (0.03 * max_val) ** 2


def ssim_map(img1: Tensor, img2: Tensor, window_size: int, max_val: float = 1.0, eps: float = 1e-12) -> Tensor:
    """Per-pixel SSIM [B, C, H, W] of two images [B, C, H, W] ('same' size, reflected borders), as kornia's: the
    moments go through kornia's `filter2d_separable` and torch."""
    from kornia.filters import filter2d_separable  # imported on first use: loading the plugins stays light

    from framework.runtime import exact_float32

    kernel = gaussian_window(window_size, img1.dtype, img1.device)  # [1, K]
    c1, c2 = ssim_constants(max_val)
    moments = torch.cat([img1, img2, img1 * img1, img2 * img2, img1 * img2], dim=1)  # [B, 5C, H, W]
    with exact_float32():  # TF32 convolutions would move SSIM by ~1e-2 (its variances cancel digits)
        filtered = filter2d_separable(moments, kernel, kernel)
    mu1, mu2, e11, e22, e12 = filtered.split(img1.shape[1], dim=1)
    mu1_sq, mu2_sq, mu1_mu2 = mu1**2, mu2**2, mu1 * mu2
    num = (2.0 * mu1_mu2 + c1) * (2.0 * (e12 - mu1_mu2) + c2)
    den = (mu1_sq + mu2_sq + c1) * ((e11 - mu1_sq) + (e22 - mu2_sq) + c2)
    return num / (den + eps)
