"""Blend-weight field: exact closest-surface weights (vs trimesh), trilinear sampling, partition of unity, cache."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from framework.rig.closest_point import closest_points
from framework.rig.weight_field import WeightField, build_weight_grid, grid_points, surface_weights


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(tmp_path))


def small_mesh():
    m = trimesh.creation.icosphere(subdivisions=2)
    v = m.vertices * np.array([1.0, 0.6, 1.8])
    v[:, 0] += 0.3 * np.sin(3 * v[:, 2])  # irregular, non-convex-ish
    rng = np.random.default_rng(0)
    w = rng.random((len(v), 5)) ** 4
    return v, m.faces, w / w.sum(1, keepdims=True)


def test_closest_points_match_trimesh():
    v, f, _ = small_mesh()
    q = np.random.default_rng(1).uniform(-2.5, 2.5, (1500, 3))
    face, bary, dist = closest_points(v, f, q)
    ref_pt, ref_dist, _ = trimesh.proximity.closest_point(trimesh.Trimesh(v, f, process=False), q)
    assert np.abs(dist - ref_dist).max() < 1e-9
    pts = (bary[:, :, None] * v[f[face]]).sum(1)
    assert np.abs(pts - ref_pt).max() < 1e-9


def test_surface_weights_vs_brute_force_trimesh():
    v, f, w = small_mesh()
    q = np.random.default_rng(2).uniform(-2.0, 2.0, (400, 3))
    got = surface_weights(v, f, w, q)
    mesh = trimesh.Trimesh(v, f, process=False)
    pt, _, tri = trimesh.proximity.closest_point(mesh, q)
    bary = trimesh.triangles.points_to_barycentric(v[f[tri]], pt)
    want = (bary[:, :, None] * w[f[tri]]).sum(1)
    assert np.abs(got - want).max() < 1e-6
    assert np.allclose(got.sum(1), 1.0)


def test_grid_sampling_nodes_sum_and_border(tmp_path):
    v, f, w = small_mesh()
    bounds = np.array([[-1.5, -1.0, -2.0], [1.5, 1.0, 2.0]])
    vol = build_weight_grid(v, f, w, bounds, resolution=9)
    field = WeightField(vol, torch.tensor(bounds, dtype=torch.float32))
    nodes = grid_points(bounds, 9).reshape(-1, 3)
    at_nodes = field.sample(torch.tensor(nodes, dtype=torch.float32))
    assert torch.allclose(at_nodes, torch.tensor(surface_weights(v, f, w, nodes), dtype=torch.float32), atol=1e-5)
    x = (torch.rand(1000, 3) * 6 - 3).requires_grad_()  # half of them outside the box
    s = field.sample(x)
    assert (s >= 0).all() and torch.allclose(s.sum(-1), torch.ones(1000), atol=1e-5)
    lo, hi = torch.tensor(bounds[0]).float(), torch.tensor(bounds[1]).float()
    assert torch.allclose(s, field.sample(torch.maximum(torch.minimum(x, hi), lo)), atol=1e-6)  # border clamp
    s[:, 0].sum().backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0


@pytest.mark.parametrize("unity", [False, True], ids=["any-volume", "partition-of-unity"])
def test_sampling_matches_grid_sample_values_and_gradients(unity):
    """The corner-bag lookup against torch's grid_sample (border padding, align_corners) on a random, non-cubic
    volume, in float64, with points inside, outside and exactly on the box faces. A volume whose nodes already sum to
    1 skips the per-lookup renormalisation: its values and gradients must still match grid_sample's renormalised
    ones (the sum of the weights is constant, so renormalising changes neither)."""
    import torch.nn.functional as F

    g = torch.Generator().manual_seed(0)
    J, D, H, W = 4, 5, 6, 7
    vol = torch.rand(J, D, H, W, generator=g) + 0.1
    if unity:
        vol = vol / vol.sum(0, keepdim=True)  # sums to 1 within float32 rounding
    vol = vol.double()  # float32 values: the field stores float32
    bounds = torch.tensor([[-1.0, -2.0, 0.5], [2.0, 1.0, 3.0]], dtype=torch.float64)
    field = WeightField(vol, bounds).double()
    assert field.partition_of_unity == unity
    lo, hi = bounds
    x = lo + (hi - lo) * (torch.rand(300, 3, generator=g, dtype=torch.float64) * 1.4 - 0.2)
    x[:10, 0] = hi[0]  # on the faces: both sides of the clamp
    x[10:20, 2] = lo[2]
    x.requires_grad_()
    ref_x = x.detach().clone().requires_grad_()
    gn = 2.0 * (ref_x - lo) / (hi - lo) - 1.0
    ref = F.grid_sample(vol[None], gn[None, None, None], mode="bilinear", padding_mode="border", align_corners=True)
    ref = ref[0, :, 0, 0].t()
    ref = ref / ref.sum(-1, keepdim=True)
    got = field.sample(x)
    # float32 rows sum to 1 within ~1e-7, so the skipped renormalisation moves values and gradients by that much
    atol = 1e-6 if unity else 1e-12
    assert torch.allclose(got, ref, atol=atol)
    proj = torch.rand(J, generator=g, dtype=torch.float64)
    (got * proj).sum().backward()
    (ref * proj).sum().backward()
    assert torch.allclose(x.grad, ref_x.grad, atol=atol if unity else 1e-10)
    assert field.volume.shape == (1, J, D, H, W)
    if unity:  # rows renormalised once, in float64
        assert torch.allclose(field.volume[0].double(), vol, atol=1e-7)
    else:
        assert torch.equal(field.volume[0].double(), vol)


def test_cache_roundtrip(tmp_path):
    v, f, w = small_mesh()
    bounds = np.array([[-1.5, -1.0, -2.0], [1.5, 1.0, 2.0]])
    a = build_weight_grid(v, f, w, bounds, resolution=6)
    files = list((tmp_path / "weight_fields").glob("*.pt"))
    assert len(files) == 1
    assert torch.equal(build_weight_grid(v, f, w, bounds, resolution=6), a)
    build_weight_grid(v, f, w, bounds, resolution=7)
    assert len(list((tmp_path / "weight_fields").glob("*.pt"))) == 2
    with pytest.raises(ValueError, match="max > min"):
        build_weight_grid(v, f, w, bounds[::-1], resolution=6)


def test_procedural_body_field_reproduces_vertex_weights_roughly():
    from plugins.body.procedural import ProceduralBody

    body = ProceduralBody(segments=8)
    lo, hi = body.rest_vertices.min(0).values - 0.05, body.rest_vertices.max(0).values + 0.05
    field = WeightField.from_body(body, torch.stack([lo, hi]), resolution=24)
    w = field.sample(body.rest_vertices)
    assert w.shape == body.skin_weights.shape
    # trilinear interpolation of a 24^3 grid blurs sharp joints; the dominant joint must still agree
    agree = (w.argmax(1) == body.skin_weights.argmax(1)).float().mean()
    assert agree > 0.95


def test_no_points():
    """Zero query points (a model pruned to nothing) give [0, J] weights and a [0, 3] gradient, with and without
    autograd."""
    vol = torch.rand(5, 4, 4, 4)
    field = WeightField(vol / vol.sum(0, keepdim=True), torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]))
    x = torch.zeros(0, 3, requires_grad=True)
    w = field.sample(x)
    w.sum().backward()
    assert w.shape == (0, 5) and x.grad.shape == (0, 3)
    with torch.no_grad():
        assert field.sample(torch.zeros(2, 0, 3)).shape == (2, 0, 5)
