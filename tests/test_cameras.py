"""Cameras.resized: images of another size see the scene at pixel coordinates scaled per axis."""

from __future__ import annotations

import torch

from framework.cameras import orbit_cameras
from framework.splat.projection import project_gaussians


def test_resized_cameras_scale_projected_centres_per_axis():
    gen = torch.Generator().manual_seed(0)
    means = 0.3 * torch.randn(50, 3, generator=gen, dtype=torch.float64)
    quats = torch.nn.functional.normalize(torch.randn(50, 4, generator=gen, dtype=torch.float64), dim=-1)
    scales = torch.full((50, 3), 0.02, dtype=torch.float64)
    opac = torch.full((50,), 0.9, dtype=torch.float64)
    cams = orbit_cameras(torch.zeros(3), 3.0, 0.0, 3, 96, 64, fov_deg=40).to("cpu", torch.float64)
    big = cams.resized(192, 96)  # x twice, y 1.5 times: a swapped axis would show
    assert (big.width, big.height) == (192, 96)
    small = project_gaussians(means, quats, scales, opac, cams.K, cams.world_to_cam, cams.width, cams.height)
    large = project_gaussians(means, quats, scales, opac, big.K, big.world_to_cam, big.width, big.height)
    expected = small.means2d * torch.tensor([2.0, 1.5], dtype=torch.float64)
    torch.testing.assert_close(large.means2d, expected, rtol=1e-12, atol=1e-9)
    assert torch.equal(cams.K, orbit_cameras(torch.zeros(3), 3.0, 0.0, 3, 96, 64, fov_deg=40).K.double())  # unchanged
