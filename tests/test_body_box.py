"""The body-box protocol (Neural Body / Animatable NeRF): the box's image against a per-pixel ray-box test, and the
region metrics against closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from framework.data.raycast import Camera, camera_rays, intrinsics, look_at
from framework.evaluation.body_box import box_corners, box_mask, box_region_metrics, frame_box
from framework.plugins import load_plugins
from framework.registry import METRICS

load_plugins()


def _rays_hit_box(cam: Camera, bounds: np.ndarray) -> np.ndarray:
    """Reference: does the ray through each pixel centre meet the box? (slab test, float64)"""
    origins, dirs = camera_rays(cam)
    o, d = origins.astype(np.float64), dirs.astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (bounds[0] - o) / d
        t1 = (bounds[1] - o) / d
    near = np.nanmax(np.minimum(t0, t1), axis=1)
    far = np.nanmin(np.maximum(t0, t1), axis=1)
    return (far >= np.maximum(near, 0)).reshape(cam.height, cam.width)


@pytest.mark.parametrize("eye", [(2.5, -1.0, 1.4), (0.3, 2.8, 0.2), (-2.0, -2.0, 2.5)])
def test_box_image_is_where_pixel_rays_meet_the_box(eye):
    bounds = np.array([[-0.3, -0.2, 0.0], [0.35, 0.25, 1.7]])
    cam = Camera(intrinsics(45.0, 96, 80), look_at(np.array(eye), np.array([0.0, 0.0, 0.85])), 96, 80)
    got = box_mask(bounds, cam.K, cam.world_to_cam, 96, 80)
    ref = _rays_hit_box(cam, bounds)
    assert ref.sum() > 200
    differ = got != ref
    assert differ.mean() < 0.002
    # a disagreement only where the outline passes within a pixel: a neighbour of each differing pixel agrees
    # with the other label
    pad = np.pad(ref, 1, mode="edge")
    near_edge = np.zeros_like(ref)
    for a in range(3):
        for b in range(3):
            near_edge |= pad[a : a + 80, b : b + 96] != ref
    assert near_edge[differ].all()


def test_frame_box_grows_the_vertex_box_by_five_centimetres():
    v = np.array([[0.0, 1.0, 2.0], [1.0, -1.0, 0.5]])
    np.testing.assert_allclose(frame_box(v), [[-0.05, -1.05, 0.45], [1.05, 1.05, 2.05]])
    assert box_corners(frame_box(v)).shape == (8, 3)


def test_region_metrics_closed_forms():
    """Inside the box the render is off by 0.1 everywhere (MSE 0.01: PSNR 20 dB); outside it is anything."""
    g = torch.Generator().manual_seed(0)
    target = torch.rand(40, 50, 3, generator=g) * 0.8
    mask = np.zeros((40, 50), bool)
    mask[5:35, 10:30] = True
    mask[5:8, 10:14] = False  # not a rectangle: the crop's zeroed corner must not count for PSNR
    inside = torch.as_tensor(mask)[..., None]
    pred = torch.where(inside, target + 0.1, torch.rand(40, 50, 3, generator=g))
    metrics = {name: METRICS.build(name) for name in ("psnr", "ssim")}
    out = box_region_metrics(pred, target, mask, metrics)
    assert out["psnr"] == pytest.approx(20.0, abs=1e-3)
    same = box_region_metrics(torch.where(inside, target, 1 - target), target, mask, metrics)
    assert same["ssim"] == pytest.approx(1.0, abs=1e-6) and same["psnr"] > 90
    tiny = np.zeros((40, 50), bool)
    tiny[10:14, 15:20] = True  # a 4x5 box inside the first: below SSIM's 11-pixel window
    small = box_region_metrics(pred, target, tiny, metrics)
    assert math.isnan(small["ssim"]) and small["psnr"] == pytest.approx(20.0, abs=1e-3)
