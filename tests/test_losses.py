"""Loss terms against hand computations, the boundary band, and the weighted composite built from configs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.ndimage import correlate1d

from framework.model.losses import CompositeLoss
from framework.plugins import load_plugins
from framework.registry import LOSSES
from framework.types import Cameras, FrameBatch, RenderOutput

load_plugins()
CONF = Path(__file__).resolve().parents[1] / "conf"


def make(b=2, h=12, w=14, seed=0, dtype=torch.float32) -> tuple[RenderOutput, FrameBatch]:
    g = torch.Generator().manual_seed(seed)
    rgb = torch.rand(b, h, w, 3, generator=g, dtype=dtype)
    alpha = torch.rand(b, h, w, 1, generator=g, dtype=dtype)
    image = torch.rand(b, h, w, 3, generator=g, dtype=dtype)
    mask = torch.zeros(b, h, w)
    mask[:, 3:9, 4:10] = 1.0
    boundary = torch.ones(b, h, w)
    boundary[:, 2:10, 3:11] = 0.0  # a band around the silhouette
    boundary[:, 4:8, 5:9] = 1.0
    cams = Cameras(torch.eye(3).expand(b, 3, 3), torch.eye(4).expand(b, 4, 4), w, h)
    render = RenderOutput(rgb=rgb, alpha=alpha, depth=None, means2d=torch.zeros(b, 0, 2), radii=torch.zeros(b, 0))
    batch = FrameBatch(image=image, mask=mask, boundary=boundary, cameras=cams, frame=torch.zeros(b, dtype=torch.long))
    return render, batch


def np64(x: torch.Tensor) -> np.ndarray:
    return x.detach().double().numpy()


@pytest.mark.parametrize("boundary", [True, False])
@pytest.mark.parametrize("foreground_only", [True, False])
def test_l1_hand(boundary, foreground_only):
    render, batch = make()
    loss = LOSSES.build("l1", boundary=boundary, foreground_only=foreground_only)(render, batch, {})
    rgb, img, mb, m = np64(render.rgb), np64(batch.image), np64(batch.boundary), np64(batch.mask)
    total = 0.0
    for b_, i, j, c in np.ndindex(*rgb.shape):
        w = (mb[b_, i, j] if boundary else 1.0) * (m[b_, i, j] if foreground_only else 1.0)
        total += w * abs(rgb[b_, i, j, c] - img[b_, i, j, c])
    assert loss.item() == pytest.approx(total / rgb.size, rel=1e-5)


def test_boundary_band_is_ignored():
    render, batch = make()
    band = (batch.boundary == 0).unsqueeze(-1)
    assert band.any()
    changed = RenderOutput(
        rgb=torch.where(band, 1.0 - render.rgb, render.rgb),
        alpha=torch.where(band, 1.0 - render.alpha, render.alpha),
        depth=None,
        means2d=render.means2d,
        radii=render.radii,
    )
    for name in ("l1", "alpha"):
        with_mb = LOSSES.build(name)
        without = LOSSES.build(name, boundary=False)
        assert with_mb(changed, batch, {}).item() == pytest.approx(with_mb(render, batch, {}).item(), abs=1e-7)
        assert abs(without(changed, batch, {}).item() - without(render, batch, {}).item()) > 1e-3
    # the gradient in the band is exactly zero
    rgb = render.rgb.clone().requires_grad_(True)
    LOSSES.build("l1")(RenderOutput(rgb, render.alpha, None, render.means2d, render.radii), batch, {}).backward()
    assert (rgb.grad[band.expand_as(rgb)] == 0).all() and (rgb.grad[~band.expand_as(rgb)] != 0).all()


@pytest.mark.parametrize("norm", ["mse", "rms", "l1"])
def test_alpha_hand(norm):
    render, batch = make(seed=3)
    loss = LOSSES.build("alpha", norm=norm)(render, batch, {})
    a, m, mb = np64(render.alpha)[..., 0], np64(batch.mask), np64(batch.boundary)
    if norm == "l1":
        expected = (mb * np.abs(a - m)).mean()
    elif norm == "mse":  # eq. 7's norm squared, per pixel
        expected = ((mb * (a - m)) ** 2).mean()
    else:  # per image ||M_b (a - m)||_2 / sqrt(H W), then the batch mean
        expected = np.mean([np.linalg.norm(mb[i] * (a[i] - m[i])) / np.sqrt(a[i].size) for i in range(len(a))])
    assert loss.item() == pytest.approx(expected, rel=1e-5)
    with pytest.raises(ValueError, match="norm"):
        LOSSES.build("alpha", norm="huber")


def test_weight_std():
    render, batch = make()
    term = LOSSES.build("weight_std")  # eq. 8's Sum_i read as a mean over Gaussians
    std = torch.rand(50, requires_grad=True)
    value = term(render, batch, {"weight_std": std})
    assert value.item() == pytest.approx(float(np64(std).mean()), rel=1e-6)
    value.backward()
    torch.testing.assert_close(std.grad, torch.full_like(std, 1 / 50))
    summed = LOSSES.build("weight_std", reduction="sum")(render, batch, {"weight_std": std})
    assert summed.item() == pytest.approx(float(np64(std).sum()), rel=1e-6)
    with pytest.raises(ValueError, match="reduction"):
        LOSSES.build("weight_std", reduction="max")
    assert term(render, batch, {}).item() == 0.0
    assert term(render, batch, {"weight_std": torch.zeros(0)}).item() == 0.0


def _ssim_map_mirror(a: np.ndarray, b: np.ndarray, window: int = 11) -> np.ndarray:
    """float64 SSIM map with the `window`-tap sigma-1.5 Gaussian and mirrored borders (d c b | a b c d)."""
    r = np.arange(window) - window // 2
    g = np.exp(-(r**2) / 4.5)
    g /= g.sum()

    def blur(x):
        return correlate1d(correlate1d(x, g, axis=0, mode="mirror"), g, axis=1, mode="mirror")

    mx, my = blur(a), blur(b)
    vx, vy, cxy = blur(a * a) - mx**2, blur(b * b) - my**2, blur(a * b) - mx * my
    return ((2 * mx * my + 1e-4) * (2 * cxy + 9e-4)) / ((mx**2 + my**2 + 1e-4) * (vx + vy + 9e-4))


def test_dssim_hand():
    render, batch = make(h=20, w=17, seed=5)
    loss = LOSSES.build("dssim")(render, batch, {})
    rgb, img = np64(render.rgb), np64(batch.image)
    maps = [_ssim_map_mirror(rgb[b, ..., c], img[b, ..., c]) for b in range(2) for c in range(3)]
    expected = np.mean([1 - m for m in maps])  # 3DGS's D-SSIM, the paper's
    assert loss.item() == pytest.approx(expected, abs=1e-5)
    assert LOSSES.build("dssim", form="half")(render, batch, {}).item() == pytest.approx(expected / 2, abs=1e-5)
    same = RenderOutput(batch.image.clone(), render.alpha, None, render.means2d, render.radii)
    assert LOSSES.build("dssim")(same, batch, {}).item() == pytest.approx(0.0, abs=1e-6)


def test_ssim_map_matches_kornia_values_and_gradients():
    """The training loss's SSIM (five moments filtered in one call) against `kornia.metrics.ssim`, float64, on a batch
    of two non-square images: same map and same gradient with respect to both images."""
    from kornia.metrics import ssim as kornia_ssim

    from framework.image.ssim import ssim_map

    g = torch.Generator().manual_seed(3)
    a = torch.rand(2, 3, 23, 31, generator=g, dtype=torch.float64, requires_grad=True)
    b = torch.rand(2, 3, 23, 31, generator=g, dtype=torch.float64, requires_grad=True)
    a2, b2 = (x.detach().clone().requires_grad_() for x in (a, b))
    proj = torch.rand(2, 3, 23, 31, generator=g, dtype=torch.float64)
    ours, ref = ssim_map(a, b, 11), kornia_ssim(a2, b2, 11, max_val=1.0)
    torch.testing.assert_close(ours, ref, rtol=0, atol=1e-12)
    (ours * proj).sum().backward()
    (ref * proj).sum().backward()
    torch.testing.assert_close(a.grad, a2.grad, rtol=0, atol=1e-12)
    torch.testing.assert_close(b.grad, b2.grad, rtol=0, atol=1e-12)


@pytest.mark.parametrize("fill", [0.0, 1.0])
def test_extremes_finite(fill):
    """Constant images (zero variance, SSIM's 0/0 case), saturated alpha, and a 1x1 image."""
    render, batch = make(h=16, w=16)
    for h, w in [(16, 16), (1, 1)]:
        rgb = torch.full((2, h, w, 3), fill, requires_grad=True)
        alpha = torch.full((2, h, w, 1), fill, requires_grad=True)
        b = FrameBatch(
            image=torch.full((2, h, w, 3), fill),
            mask=torch.full((2, h, w), fill),
            boundary=torch.ones(2, h, w),
            cameras=batch.cameras,
            frame=batch.frame,
        )
        r = RenderOutput(rgb, alpha, None, render.means2d, render.radii)
        total = sum(LOSSES.build(n)(r, b, {}) for n in ("l1", "alpha", "dssim", "weight_std"))
        total.backward()
        assert torch.isfinite(total) and torch.isfinite(rgb.grad).all() and torch.isfinite(alpha.grad).all()


def test_bfloat16_inputs():
    render, batch = make(h=16, w=16, dtype=torch.bfloat16)
    ref_render, ref_batch = make(h=16, w=16)
    for name in ("l1", "alpha", "dssim"):
        lo = LOSSES.build(name)(render, batch, {})
        hi = LOSSES.build(name)(ref_render, ref_batch, {})
        assert torch.isfinite(lo) and abs(lo.float().item() - hi.item()) < 0.02


def test_lpips_loss_matches_module():
    entry = LOSSES.entry("lpips")
    if entry.unavailable_reason() is not None:
        pytest.skip(entry.unavailable_reason())
    from framework.image.lpips import LPIPS

    render, batch = make(h=32, w=40)
    rgb = render.rgb.clone().requires_grad_(True)
    term = LOSSES.build("lpips")
    value = term(RenderOutput(rgb, render.alpha, None, render.means2d, render.radii), batch, {})
    expected = LPIPS("alex")(render.rgb.permute(0, 3, 1, 2), batch.image.permute(0, 3, 1, 2), normalize=True).mean()
    assert value.item() == pytest.approx(expected.item(), rel=1e-5)
    value.backward()
    assert torch.isfinite(rgb.grad).all() and rgb.grad.abs().sum() > 0
    assert list(term.parameters()) == [] and term.state_dict() == {}  # backbone kept out of checkpoints/optimizers


def test_composite_weights_and_values():
    render, batch = make()
    aux = {"weight_std": torch.tensor([0.2, 0.4])}
    comp = CompositeLoss(
        {
            "l1": {"weight": 0.8, "boundary": True},
            "alpha": {"weight": 10.0},
            "weight_std": {"weight": 0.2},
            "l1_fg": {"name": "l1", "weight": 0.5, "foreground_only": True},
        }
    )
    total, values = comp(render, batch, aux)
    parts = {
        "l1": LOSSES.build("l1")(render, batch, aux),
        "alpha": LOSSES.build("alpha")(render, batch, aux),
        "weight_std": torch.tensor(0.3),
        "l1_fg": LOSSES.build("l1", foreground_only=True)(render, batch, aux),
    }
    for k, v in parts.items():
        assert values[k].item() == pytest.approx(v.item(), rel=1e-6)
        assert not values[k].requires_grad
    expected = 0.8 * parts["l1"] + 10 * parts["alpha"] + 0.2 * 0.3 + 0.5 * parts["l1_fg"]
    assert total.item() == pytest.approx(expected.item(), rel=1e-6)


def test_aux_keys_name_what_the_built_terms_read():
    """A term with weight 0 is not built, so the deformer is not asked for its aux output (no six-point lookups)."""
    comp = CompositeLoss({"l1": {"weight": 0.8}, "weight_std": {"weight": 0.0}, "fg": {"name": "l1", "weight": 1.0}})
    assert comp.aux_keys == frozenset()
    assert CompositeLoss({"smooth": {"name": "weight_std", "weight": 0.2}}).aux_keys == {"weight_std"}
