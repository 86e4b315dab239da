"""PSNR / SSIM / LPIPS metrics against closed forms and an independent float64 SSIM."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.ndimage import correlate1d

from framework.plugins import load_plugins
from framework.registry import METRICS

load_plugins()


def ssim_reference(a: np.ndarray, b: np.ndarray) -> float:
    """Wang et al. SSIM in float64, [H, W, C] in [0, 1]: 11-tap Gaussian (sigma 1.5) window, valid region only,
    population (not sample) statistics, K1 0.01, K2 0.03, mean over channels (scikit-image's gaussian mode)."""
    r = np.arange(11) - 5
    g = np.exp(-(r**2) / (2 * 1.5**2))
    g /= g.sum()

    def blur(x: np.ndarray) -> np.ndarray:
        y = correlate1d(correlate1d(x, g, axis=0, mode="constant"), g, axis=1, mode="constant")
        return y[5:-5, 5:-5]  # keep only windows fully inside the image

    c1, c2 = 0.01**2, 0.03**2
    vals = []
    for c in range(a.shape[-1]):
        x, y = a[..., c].astype(np.float64), b[..., c].astype(np.float64)
        mx, my = blur(x), blur(y)
        vx, vy, cxy = blur(x * x) - mx**2, blur(y * y) - my**2, blur(x * y) - mx * my
        s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx**2 + my**2 + c1) * (vx + vy + c2))
        vals.append(s.mean())
    return float(np.mean(vals))


def test_psnr_closed_form():
    psnr = METRICS.build("psnr")
    target = torch.rand(3, 16, 20, 3) * 0.5
    offsets = torch.tensor([0.1, 0.01, 0.25])
    pred = target + offsets.view(3, 1, 1, 1)  # MSE = offset^2 exactly
    expected = torch.tensor([-20 * math.log10(o) for o in offsets.tolist()])
    torch.testing.assert_close(psnr(pred, target), expected, rtol=0, atol=1e-4)
    assert psnr.higher_is_better


def test_psnr_identical_and_mixed_error():
    psnr = METRICS.build("psnr")
    t = torch.rand(2, 8, 8, 3)
    p = t.clone()
    p[1, 0, 0, 0] += 1.0  # one pixel channel off by 1: MSE = 1 / (8*8*3)
    out = psnr(p, t)
    assert out[0].item() == pytest.approx(100.0)  # MSE floor instead of inf
    assert out[1].item() == pytest.approx(10 * math.log10(8 * 8 * 3), abs=1e-4)


def test_ssim_matches_float64_reference():
    ssim = METRICS.build("ssim")
    rng = np.random.default_rng(0)
    base = rng.random((2, 40, 33, 3)).astype(np.float32)
    yy, xx = np.mgrid[0:40, 0:33]
    smooth = (0.5 + 0.4 * np.sin(xx / 3.0) * np.cos(yy / 5.0))[..., None].repeat(3, -1).astype(np.float32)
    target = np.stack([base[0], smooth])
    pred = np.clip(target + 0.1 * rng.standard_normal(target.shape).astype(np.float32), 0, 1)
    got = ssim(torch.from_numpy(pred), torch.from_numpy(target))
    ref = [ssim_reference(pred[i], target[i]) for i in range(2)]
    np.testing.assert_allclose(got.numpy(), ref, atol=1e-4)
    same = ssim(torch.from_numpy(target), torch.from_numpy(target))
    np.testing.assert_allclose(same.numpy(), 1.0, atol=1e-5)


def test_ssim_small_image_error_and_shape_error():
    ssim = METRICS.build("ssim")
    with pytest.raises(ValueError, match="at least 11x11"):
        ssim(torch.zeros(1, 8, 8, 3), torch.zeros(1, 8, 8, 3))
    with pytest.raises(ValueError, match=r"\[B, H, W, 3\]"):
        ssim(torch.zeros(1, 16, 16, 3), torch.zeros(1, 16, 16, 4))


def test_lpips_metrics():
    alex_entry = METRICS.entry("lpips_alex")
    if alex_entry.unavailable_reason() is not None:
        pytest.skip(alex_entry.unavailable_reason())
    alex, vgg = METRICS.build("lpips_alex"), METRICS.build("lpips_vgg", batch_size=1)
    assert not alex.higher_is_better and not vgg.higher_is_better
    torch.manual_seed(0)
    t = torch.rand(3, 36, 36, 3)
    p = (t + 0.2 * torch.randn_like(t)).clamp(0, 1)
    p[2] = t[2]
    for metric in (alex, vgg):
        d = metric(p, t)
        assert d.shape == (3,) and torch.isfinite(d).all()
        assert d[0] > 0.01 and d[1] > 0.01 and d[2].abs() < 1e-6
    # [0, 1] inputs go through the same network as the [-1, 1] module call
    from framework.image.lpips import LPIPS

    direct = LPIPS("alex")(p.permute(0, 3, 1, 2) * 2 - 1, t.permute(0, 3, 1, 2) * 2 - 1)
    torch.testing.assert_close(alex(p, t), direct.detach(), rtol=1e-5, atol=1e-6)
    assert alex(p[:0], t[:0]).shape == (0,)
