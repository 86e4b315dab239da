"""Deformers: identity pose, rigid motion of the whole skeleton, partition of unity, baking, extremes."""

from __future__ import annotations

import math

import pytest
import torch

from framework.geometry import axis_angle_to_rotmat, quat_to_rotmat
from framework.model.gaussian_init import from_body_surface
from framework.registry import REGISTRIES
from framework.splat.sh import eval_sh
from framework.types import Gaussians


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(tmp_path))


@pytest.fixture(scope="module")
def body():
    from plugins.body.procedural import ProceduralBody

    return ProceduralBody(segments=8)


def bounds_of(body):
    return torch.stack([body.rest_vertices.min(0).values - 0.1, body.rest_vertices.max(0).values + 0.1])


def make(name, body, **kw):
    from framework.plugins import load_plugins

    load_plugins()
    d = REGISTRIES["deformer"].build(name, grid_resolution=12, **kw)
    d.bind(body, bounds_of(body))
    return d


def canonical(body, n=300, seed=0) -> Gaussians:
    g = from_body_surface(body, n, seed=seed)
    return g.replace(sh=torch.randn(g.sh.shape, generator=torch.Generator().manual_seed(seed)) * 0.3)


def covariance(g: Gaussians) -> torch.Tensor:
    R = quat_to_rotmat(g.quats)
    return R @ torch.diag_embed(g.scales**2) @ R.mT


@pytest.mark.parametrize("name", ["lbs", "lbs_residual"])
def test_identity_pose_is_identity(body, name):
    g = canonical(body)
    out = make(name, body)(g, body.bone_transforms(torch.zeros(1, body.num_joints, 3))[0])
    p = out.posed
    assert torch.allclose(p.means, g.means, atol=1e-6)
    assert torch.allclose(covariance(p), covariance(g), atol=1e-7)
    assert torch.allclose(p.log_scales, g.log_scales, atol=1e-6)
    assert torch.allclose(p.sh, g.sh, atol=1e-5)
    assert torch.allclose(out.weights.sum(-1), torch.ones(g.num), atol=1e-5) and (out.weights >= 0).all()


@pytest.mark.parametrize("name", ["lbs", "lbs_residual"])
def test_rigid_skeleton_motion_moves_gaussians_rigidly(body, name):
    g = canonical(body)
    pose = torch.zeros(1, body.num_joints, 3)
    pose[0, 0] = torch.tensor([0.4, -1.1, 2.0])  # root rotation only: every bone gets the same rigid transform
    T = body.bone_transforms(pose)[0]
    T = torch.cat([T[:, :3, :3], T[:, :3, 3:] + torch.tensor([[0.3], [-0.2], [1.0]])], dim=-1)
    T = torch.cat([T, torch.tensor([0.0, 0.0, 0.0, 1.0]).expand(T.shape[0], 1, 4)], dim=1)
    M = T[0]
    R, t = M[:3, :3], M[:3, 3]
    p = make(name, body)(g, T).posed
    assert torch.allclose(p.means, g.means @ R.T + t, atol=1e-5)
    assert torch.allclose(covariance(p), R @ covariance(g) @ R.T, atol=1e-6)
    d = torch.randn(g.num, 3)  # colour seen along d after posing == colour seen along R^T d before
    assert torch.allclose(eval_sh(3, p.sh, d), eval_sh(3, g.sh, d @ R), atol=1e-5)


def test_uniform_scale_goes_to_scales(body):
    g = canonical(body, 50)
    T = torch.diag(torch.tensor([2.0, 2.0, 2.0, 1.0])).expand(body.num_joints, 4, 4)
    p = make("lbs", body)(g, T).posed
    assert torch.allclose(p.log_scales, g.log_scales + math.log(2.0), atol=1e-5)
    assert torch.allclose(p.means, 2 * g.means, atol=1e-6)
    p = make("lbs", body, stretch="none")(g, T).posed
    assert torch.allclose(p.log_scales, g.log_scales)


def perturbed_residual(body):
    d = make("lbs_residual", body)
    torch.manual_seed(0)
    with torch.no_grad():
        for prm in d.mlp.parameters():
            prm.add_(torch.randn_like(prm) * 0.5)
    return d


def test_residual_weights_partition_of_unity_and_baking(body):
    d = perturbed_residual(body)
    g = canonical(body)
    pose = torch.randn(1, body.num_joints, 3) * 0.4
    T = body.bone_transforms(pose)[0]
    out = d(g, T)
    w = out.weights
    assert (w >= 0).all() and torch.allclose(w.sum(-1), torch.ones(g.num), atol=1e-5)
    assert not torch.allclose(w, make("lbs", body).weights(g.means), atol=1e-3)  # the residual does something
    baked = g.replace(skin_weights=d.bake(g))
    out_b = d(baked, T)
    for k in ("means", "quats", "log_scales", "sh"):
        assert torch.allclose(getattr(out_b.posed, k), getattr(out.posed, k), atol=1e-6), k
    # baked weights need no field or MLP at all: a plain lbs deformer gives the same result
    out_plain = make("lbs", body)(baked, T)
    assert torch.allclose(out_plain.posed.means, out.posed.means, atol=1e-6)


def test_disabled_residual_equals_lbs_and_uses_no_params(body):
    d = perturbed_residual(body)
    d.enabled = False
    g = canonical(body)
    g = g.replace(means=g.means.clone().requires_grad_())
    T = body.bone_transforms(torch.randn(1, body.num_joints, 3) * 0.4)[0]
    a, b = d(g, T), make("lbs", body)(g, T)
    assert torch.allclose(a.posed.means, b.posed.means, atol=1e-7)
    (a.posed.means.sum() + a.aux["weight_std"].sum()).backward()
    assert all(p.grad is None for p in d.mlp.parameters())


def test_antipodal_blend_and_gradients_finite(body):
    g = canonical(body, 200)
    params = {k: getattr(g, k).clone().requires_grad_() for k in ("means", "quats", "log_scales", "sh")}
    g = g.replace(**params)
    J = body.num_joints
    T = torch.eye(4).repeat(J, 1, 1)
    T[1::2, :3, :3] = axis_angle_to_rotmat(torch.tensor([math.pi, 0.0, 0.0]))  # half the bones flipped by 180 deg
    w = torch.zeros(g.num, J)
    w[:, 0], w[:, 1] = 0.5, 0.5  # antipodal 50/50 blend: rank-1 matrix
    out = make("lbs_residual", body)(g.replace(skin_weights=w), T)
    pos = body.bone_transforms(torch.randn(1, J, 3) * 1.5)[0]
    out2 = make("lbs_residual", body)(g, pos)
    loss = sum(
        v.float().sum()
        for o in (out, out2)
        for v in (o.posed.means, o.posed.quats, o.posed.log_scales, o.posed.sh, o.aux["weight_std"])
    )
    loss.backward()
    for o in (out, out2):
        for v in (o.posed.means, o.posed.quats, o.posed.log_scales, o.posed.sh):
            assert torch.isfinite(v).all()
    for k, v in params.items():
        assert torch.isfinite(v.grad).all(), k
    assert out2.aux["weight_std"].shape == (g.num,) and (out2.aux["weight_std"] >= 0).all()


def test_weight_std_matches_direct_computation(body):
    d = make("lbs", body)
    g = canonical(body, 40)
    std = d(g, torch.eye(4).repeat(body.num_joints, 1, 1)).aux["weight_std"]
    R = quat_to_rotmat(g.quats)
    pts = []
    for sign in (1.0, -1.0):
        for axis in range(3):
            pts.append(g.means + sign * g.scales[:, axis : axis + 1] * R[:, :, axis])
    w6 = torch.stack([d.weights(p) for p in pts], dim=1)  # [N, 6, J]
    want = ((w6 - w6.mean(1, keepdim=True)) ** 2).mean(1).sqrt().sum(-1)
    assert torch.allclose(std, want, atol=1e-5)


def test_identity_deformer_and_errors(body):
    from framework.plugins import load_plugins

    load_plugins()
    g = canonical(body, 10)
    out = REGISTRIES["deformer"].build("identity")(g, None)
    assert out.posed is g and out.weights is None
    d = make("lbs", body)
    with pytest.raises(ValueError, match="bone_transforms"):
        d(g, None)
    with pytest.raises(ValueError, match="joints"):
        d(g, torch.eye(4).repeat(3, 1, 1))
    with pytest.raises(ValueError, match="identity"):
        REGISTRIES["deformer"].build("lbs").bind(None, None)


def test_baked_weights_match_a_float64_svd_reference(body):
    """Baked weights where most rows hang on one bone (some with a weight below 1, one negative, one bone stretched):
    every posed attribute must match LBS computed row by row in float64 with the rotation from an SVD."""
    g = canonical(body, 240, seed=3)
    J = body.num_joints
    gen = torch.Generator().manual_seed(5)
    T = body.bone_transforms(torch.randn(1, J, 3, generator=gen) * 0.8)[0]  # [J, 4, 4]
    T[2, :3, :3] *= torch.tensor([1.3, 0.8, 1.1])  # one bone with a stretch, so S is not the identity there
    w = torch.zeros(g.num, J)
    bones = torch.randint(0, J, (g.num,), generator=gen)
    w[torch.arange(g.num), bones] = 1.0
    w[:40, (bones[:40] + 1) % J] = 0.3  # 40 blended rows
    w[40:50] *= 0.7  # single bone, weight 0.7: A = 0.7 A_k, whose rotation is still the bone's
    w[50, bones[50]] = -1.0  # single negative weight: a reflection, not a rigid row
    out = make("lbs", body)(g.replace(skin_weights=w), T).posed

    w64, T64 = w.double(), T.double()
    P = torch.einsum("nj,jab->nab", w64, T64[:, :3, :])  # [N, 3, 4]
    A, t = P[:, :, :3], P[:, :, 3]
    U, _, Vh = torch.linalg.svd(A)
    d = torch.sign(torch.linalg.det(U @ Vh))
    R = U @ torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1)) @ Vh  # closest rotation
    S = R.mT @ A
    axes = quat_to_rotmat(g.quats.double())
    k = torch.einsum("nil,nij,njl->nl", axes, 0.5 * (S + S.mT), axes)
    torch.testing.assert_close(
        out.means.double(), (A @ g.means.double().unsqueeze(-1)).squeeze(-1) + t, atol=2e-5, rtol=0
    )
    torch.testing.assert_close(quat_to_rotmat(out.quats).double(), R @ axes, atol=2e-5, rtol=0)
    ok = k > 1e-6  # the negative row's stretch is clamped at the floor
    torch.testing.assert_close(
        out.log_scales.double()[ok], (g.log_scales.double() + torch.log(k))[ok], atol=2e-5, rtol=0
    )
