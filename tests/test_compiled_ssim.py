"""The compiled SSIM of CPU training steps (`framework.kernels.ssim`, its filter `separable_filter`) against
scipy's mirrored correlation and kornia's SSIM and filter, values and gradients in float64, and against the torch
path of `ssim_map` in float32."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.ndimage import correlate1d

from framework.execution import COMPILED
from framework.image.ssim import ssim_map
from framework.kernels import ssim as compiled_ssim
from framework.kernels.separable_filter import filter_planes


def _filter(x: np.ndarray, kx: np.ndarray, ky: np.ndarray, adjoint: bool) -> np.ndarray:
    out, work = np.empty_like(x), np.empty_like(x)
    filter_planes(x, kx, ky, adjoint, 0, x.shape[0], work, out)
    return out


@pytest.mark.parametrize(
    ("shape", "kx", "ky"),
    [
        ((3, 23, 31), 11, 11),  # the SSIM window on a non-square plane
        ((2, 6, 9), 11, 5),  # a window reaching the far edge: radius 5 on 6 rows reflects from the last row
        ((1, 1, 4), 7, 1),  # one row: a 1-tap kernel along H
        ((4, 16, 16), 3, 9),
    ],
)
def test_filter_matches_scipy_and_its_adjoint_kornias_gradient(shape, kx, ky):
    """Asymmetric random taps, so that an adjoint that flipped the taps or dropped the mirrored scatter fails."""
    from kornia.filters import filter2d_separable

    g = np.random.default_rng(sum(shape) + kx)
    x, taps_x, taps_y = g.random(shape), g.random(kx), g.random(ky)
    # scipy's 'mirror' is torch's 'reflect' (d c b | a b c d); correlation along W first, then H, as kornia
    ref = correlate1d(correlate1d(x, taps_x, axis=-1, mode="mirror"), taps_y, axis=-2, mode="mirror")
    np.testing.assert_allclose(_filter(x, taps_x, taps_y, False), ref, rtol=1e-13, atol=1e-13)

    proj = g.random(shape)
    xt = torch.from_numpy(x)[None].requires_grad_()
    kernels = (torch.from_numpy(taps_x)[None], torch.from_numpy(taps_y)[None])
    (filter2d_separable(xt, *kernels) * torch.from_numpy(proj)[None]).sum().backward()
    np.testing.assert_allclose(_filter(proj, taps_x, taps_y, True), xt.grad[0].numpy(), rtol=0, atol=1e-12)


@pytest.mark.parametrize("shape", [(2, 3, 23, 31), (1, 4, 12, 6)])
def test_ssim_matches_kornia_values_and_both_gradients(monkeypatch, shape):
    from kornia.metrics import ssim as kornia_ssim

    monkeypatch.setattr(compiled_ssim, "MIN_PIXELS_PER_CHUNK", 1)  # planes split over the threads
    g = torch.Generator().manual_seed(sum(shape))
    a = torch.rand(shape, generator=g, dtype=torch.float64, requires_grad=True)
    b = torch.rand(shape, generator=g, dtype=torch.float64, requires_grad=True)
    a2, b2 = (x.detach().clone().requires_grad_() for x in (a, b))
    window = min(11, 2 * min(shape[-2:]) - 1)
    ours, ref = compiled_ssim.ssim_map(a, b, window), kornia_ssim(a2, b2, window, max_val=1.0)
    torch.testing.assert_close(ours, ref, rtol=0, atol=1e-12)
    proj = torch.rand(shape, generator=g, dtype=torch.float64)
    (ours * proj).sum().backward()
    (ref * proj).sum().backward()
    torch.testing.assert_close(a.grad, a2.grad, rtol=0, atol=1e-11)
    torch.testing.assert_close(b.grad, b2.grad, rtol=0, atol=1e-11)


def test_gradcheck_on_near_constant_images():
    """Finite differences where SSIM's variances are small (the c2-dominated regime of flat render regions)."""
    g = torch.Generator().manual_seed(1)
    a = (0.5 + 1e-3 * torch.rand(1, 2, 7, 8, generator=g, dtype=torch.float64)).requires_grad_()
    b = torch.rand(1, 2, 7, 8, generator=g, dtype=torch.float64).requires_grad_()
    assert torch.autograd.gradcheck(lambda x, y: compiled_ssim.ssim_map(x, y, 5), (a, b))


def test_float32_same_as_the_torch_path():
    """float32 images of a training render's size: the same map and gradient as kornia's filter and torch, to rounding
    (SSIM's variances subtract squared means, which amplifies the moments' float32 rounding to ~1e-6)."""
    g = torch.Generator().manual_seed(4)
    a = torch.rand(1, 3, 40, 56, generator=g, requires_grad=True)
    b = torch.rand(1, 3, 40, 56, generator=g)
    a2 = a.detach().clone().requires_grad_()
    ours, ref = compiled_ssim.ssim_map(a, b, 11), ssim_map(a2, b, 11)
    assert ours.dtype == torch.float32
    torch.testing.assert_close(ours, ref, rtol=0, atol=1e-5)
    ours.mean().backward()
    ref.mean().backward()
    torch.testing.assert_close(a.grad, a2.grad, rtol=1e-4, atol=1e-9)


def test_applies_only_to_cpu_floats_and_rejects_a_window_too_large():
    x = torch.rand(1, 3, 4, 20)
    assert COMPILED.compiled(x) and COMPILED.compiled(x.double()) and not COMPILED.compiled(x.half())
    assert not COMPILED.compiled(x.to(torch.device("meta")))
    with pytest.raises(ValueError, match="11-tap window on 4 x 20"):
        compiled_ssim.ssim_map(x, x, 11)
