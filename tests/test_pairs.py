"""The shared (Gaussian, pixel) pair list (framework/splat/pairs.py) against a float64 brute force over every pixel."""

from __future__ import annotations

import pytest
import torch

from framework.splat.contract import ALPHA_MIN
from framework.splat.pairs import depth_ordered_entries, enumerate_pairs, sort_pairs_by_pixel
from framework.splat.projection import project_gaussians
from framework.testing.conformance import make_random_scene


@pytest.mark.parametrize("seed,cams", [(0, 1), (1, 2), (2, 3)])
def test_pairs_cover_every_contributing_pixel_in_depth_order(seed: int, cams: int) -> None:
    """Every (Gaussian, pixel) whose pixel centre has alpha >= 1/255 in float64 is listed; the list is sorted by pixel
    and, inside a pixel, by depth; and it wastes little (most listed pairs do contribute)."""
    W, H = 40, 32
    s = make_random_scene(seed, 50, W, H, dtype=torch.float64, num_cameras=cams, sh_degree=0)
    K, w2c = s.cameras.K, s.cameras.world_to_cam
    proj = project_gaussians(s.means, s.quats, s.scales, s.opacities, K, w2c, W, H)
    flat, cam, gid = depth_ordered_entries(proj.valid, proj.depths)
    m2d = proj.means2d.reshape(-1, 2)[flat]
    con = proj.conics.reshape(-1, 3)[flat]
    ent, pix = enumerate_pairs(m2d, con, s.opacities[gid], proj.half_extents.reshape(-1, 2)[flat], cam, W, H)
    ent, pix = sort_pairs_by_pixel(ent, pix, cams * H * W)

    # brute force: alpha of every entry at every pixel centre of its camera
    ys, xs = torch.meshgrid(
        torch.arange(H, dtype=torch.float64) + 0.5, torch.arange(W, dtype=torch.float64) + 0.5, indexing="ij"
    )
    dx = m2d[:, 0, None, None] - xs  # [M, H, W]
    dy = m2d[:, 1, None, None] - ys
    sigma = 0.5 * (con[:, 0, None, None] * dx**2 + con[:, 2, None, None] * dy**2) + con[:, 1, None, None] * dx * dy
    alpha = s.opacities[gid][:, None, None] * torch.exp(-sigma)
    e_ref, local = torch.nonzero((alpha >= ALPHA_MIN).reshape(len(flat), -1), as_tuple=True)
    truth = set(zip(e_ref.tolist(), (cam[e_ref] * H * W + local).tolist(), strict=True))
    listed = set(zip(ent.tolist(), pix.tolist(), strict=True))
    assert len(truth) > 50
    assert truth <= listed, f"{len(truth - listed)} contributing pairs missing"
    assert len(listed) <= 1.5 * len(truth)  # the ellipse spans, not the boxes
    assert len(listed) == ent.shape[0]  # no pair twice
    assert bool((pix[1:] >= pix[:-1]).all())
    same = pix[1:] == pix[:-1]
    depth = proj.depths.reshape(-1)[flat]
    assert bool((depth[ent[1:]][same] >= depth[ent[:-1]][same]).all())


def test_wide_pixel_indices_sort_like_int64() -> None:
    """Above 2**16 pixels the keys are int32: the order is a stable int64 sort's."""
    g = torch.Generator().manual_seed(0)
    for num_pixels in (100, 2**16, 2**16 + 1, 3 * 160 * 160):
        pix = torch.randint(0, num_pixels, (5000,), generator=g)
        ent = torch.arange(5000)
        e, p = sort_pairs_by_pixel(ent, pix, num_pixels)
        ref_p, perm = torch.sort(pix, stable=True)
        assert torch.equal(p, ref_p) and torch.equal(e, ent[perm]) and p.dtype == torch.int64


def test_row_bands_one_band_only_when_the_boxes_fit_the_budget() -> None:
    """One band comes back only when the boxes' rows x columns (counted here box by box, pixel by pixel) fit the
    budget, and a budget they exceed splits the image: random boxes, budgets on both sides of their count."""
    from framework.splat.bands import row_bands

    g = torch.Generator().manual_seed(3)
    W, H = 40, 30
    for trial in range(20):
        m = torch.rand(12, 2, generator=g) * torch.tensor([W, H]) * 1.4 - 5
        h = torch.rand(12, 2, generator=g) * 6
        count = 0
        for (mx, my), (hx, hy) in zip(m.tolist(), h.tolist(), strict=True):
            cols = sum(1 for x in range(W) if mx - hx - 1 <= x + 0.5 <= mx + hx + 1)
            rows = sum(1 for y in range(H) if my - hy - 1 <= y + 0.5 <= my + hy + 1)
            count += cols * rows
        for budget in (count // 4, count * 4 + 1000):
            bands = row_bands(m, h, W, H, max_pairs=budget)
            assert bands[0][0] == 0 and bands[-1][1] == H
            if len(bands) == 1:
                assert count <= budget or budget == count * 4 + 1000, (trial, count, budget)
        assert len(row_bands(m, h, W, H, max_pairs=max(1, count // 4))) > 1 or count == 0


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_row_bands_plan_on_the_gaussians_device() -> None:
    """The band planner keeps its counters on the Gaussians' device: CUDA boxes give the bands CPU boxes give (a
    CPU-only counter failed torch_ref at 200k Gaussians at 512 px on an H200, the first render large enough to need
    bands)."""
    from framework.splat.bands import row_bands

    g = torch.Generator().manual_seed(5)
    W, H = 64, 48
    m = torch.rand(200, 2, generator=g) * torch.tensor([W, H])
    h = torch.rand(200, 2, generator=g) * 8
    cpu = row_bands(m, h, W, H, max_pairs=500)
    assert len(cpu) > 1
    assert row_bands(m.cuda(), h.cuda(), W, H, max_pairs=500) == cpu
