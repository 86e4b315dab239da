"""Canonical Gaussian initialisation and positional encoding."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from framework.geometry import quat_to_rotmat
from framework.model.gaussian_init import from_mesh_surface, from_points, random_in_box
from framework.model.posenc import normalize_to_bounds, posenc, posenc_dim
from framework.splat.sh import sh0_to_rgb


def test_posenc_layout_and_dims():
    x = torch.tensor([[0.25, -0.5, 1.0]])
    e = posenc(x, 1)
    assert e.shape == (1, 9) == (1, posenc_dim(1)) and posenc_dim(3) == 21
    assert torch.allclose(e[0, 3:6], torch.sin(math.pi * x[0])) and torch.allclose(e[0, 6:9], torch.cos(math.pi * x[0]))
    assert torch.allclose(posenc(x, 3)[0, 15:18], torch.sin(4 * math.pi * x[0]))
    b = torch.tensor([[0.0, 0.0, 0.0], [2.0, 4.0, 8.0]])
    assert torch.allclose(normalize_to_bounds(b, b), torch.tensor([[-1.0] * 3, [1.0] * 3]))


def test_surface_init_on_sphere():
    m = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    g = from_mesh_surface(m.vertices, m.faces, 3000, sh_degree=3, seed=3, opacity=0.2, color=(0.8, 0.2, 0.1))
    assert (g.means.norm(dim=1) - 0.5).abs().max() < 5e-3  # on the (faceted) surface
    R = quat_to_rotmat(g.quats)
    n = g.means / g.means.norm(dim=1, keepdim=True)
    assert (R[:, :, 2] * n).sum(-1).abs().min() > 0.98  # thin axis along the normal
    assert (g.log_scales[:, 2] < g.log_scales[:, 0]).all()
    # spacing ~ sqrt(area / N) for uniform area sampling
    expect = math.sqrt(4 * math.pi * 0.25 / 3000)
    assert 0.2 * expect < g.scales[:, 0].median() < 2 * expect
    assert torch.allclose(sh0_to_rgb(g.sh[:, 0]), torch.tensor([0.8, 0.2, 0.1]).expand(3000, 3), atol=1e-6)
    assert g.sh.shape == (3000, 16, 3) and (g.sh[:, 1:] == 0).all()
    assert torch.allclose(torch.sigmoid(g.opacity_logits), torch.full((3000,), 0.2))
    lo, hi = torch.tensor(m.vertices.min(0)), torch.tensor(m.vertices.max(0))
    want = posenc(normalize_to_bounds(g.means.double(), torch.stack([lo, hi])), 1).float()
    assert g.latents.shape == (3000, 9) and torch.allclose(g.latents, want, atol=1e-5)
    # area weighting: the upper hemisphere holds about half the samples
    assert abs((g.means[:, 2] > 0).float().mean() - 0.5) < 0.05
    g2 = from_mesh_surface(m.vertices, m.faces, 3000, seed=3)
    assert torch.equal(g2.means, g.means)  # deterministic for a seed


def test_points_and_box_init():
    pts = np.random.default_rng(0).random((200, 3))
    g = from_points(pts, sh_degree=1, colors=np.full((200, 3), 0.3))
    assert g.sh.shape == (200, 4, 3) and torch.allclose(sh0_to_rgb(g.sh[:, 0]), torch.full((200, 3), 0.3))
    assert torch.allclose(g.quats, torch.tensor([1.0, 0, 0, 0]).expand(200, 4))
    b = torch.tensor([[0.0, -1.0, 2.0], [1.0, 1.0, 3.0]])
    g = random_in_box(b, 500, seed=1)
    assert (g.means >= b[0]).all() and (g.means <= b[1]).all() and torch.isfinite(g.log_scales).all()
    with pytest.raises(ValueError, match="max > min"):
        random_in_box(b.flip(0), 10)
    with pytest.raises(ValueError, match="opacity"):
        random_in_box(b, 10, opacity=1.0)
