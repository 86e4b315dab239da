"""Forward kinematics and LBS against a naive float64 per-joint loop, closed forms and gradcheck."""

from __future__ import annotations

import math

import pytest
import torch

from framework.rig.kinematics import (
    blend_transforms,
    forward_kinematics,
    forward_kinematics_rotmat,
    kinematic_levels,
    skin_points,
)

# a tree whose joint order is NOT topological (children listed before some parents)
PARENTS = [-1, 0, 5, 1, 3, 0, 2, 0, 7, 8, 8]


def _rodrigues64(aa: torch.Tensor) -> torch.Tensor:
    """Independent rotation from the matrix exponential of the skew matrix."""
    x, y, z = aa.double().tolist()
    K = torch.tensor([[0, -z, y], [z, 0, -x], [-y, x, 0]], dtype=torch.float64)
    return torch.linalg.matrix_exp(K)


def naive_fk(pose: torch.Tensor, joints: torch.Tensor, parents: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-batch, per-joint float64 loop in dependency order: G_k = G_p @ [R_k | j_k - j_p]."""
    B, J = pose.shape[:2]
    G = torch.zeros(B, J, 4, 4, dtype=torch.float64)
    T = torch.zeros_like(G)
    for b in range(B):
        done: dict[int, torch.Tensor] = {}
        while len(done) < J:
            for k in range(J):
                p = parents[k]
                if k in done or (p >= 0 and p not in done):
                    continue
                L = torch.eye(4, dtype=torch.float64)
                L[:3, :3] = _rodrigues64(pose[b, k])
                jb = joints[b] if joints.dim() == 3 else joints
                L[:3, 3] = (jb[k] - (jb[p] if p >= 0 else 0)).double()
                done[k] = L if p < 0 else done[p] @ L
                Tk = torch.eye(4, dtype=torch.float64)
                Tk[:3, 3] = -jb[k].double()
                G[b, k], T[b, k] = done[k], done[k] @ Tk
    return G, T


def _random(B: int = 3, seed: int = 0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    J = len(PARENTS)
    return (torch.randn(B, J, 3, generator=g, dtype=dtype) * 1.2, torch.randn(J, 3, generator=g, dtype=dtype) * 0.5)


def test_levels_group_joints_by_depth():
    levels = kinematic_levels(PARENTS)
    depth = {}
    for d, (ids, local) in enumerate(levels):
        for j, pos in zip(ids, local or [None] * len(ids), strict=True):
            depth[j] = d
            if d:
                assert levels[d - 1][0][pos] == PARENTS[j]
    assert sorted(depth) == list(range(len(PARENTS)))
    with pytest.raises(ValueError, match="one root"):
        kinematic_levels([-1, -1, 0])
    with pytest.raises(ValueError, match="tree"):
        kinematic_levels([-1, 2, 1])


def test_matches_naive_loop_float64():
    pose, joints = _random()
    G, T = forward_kinematics(pose, joints, torch.tensor(PARENTS))
    G_ref, T_ref = naive_fk(pose, joints, PARENTS)
    assert (G - G_ref).abs().max() < 1e-12
    assert (T - T_ref).abs().max() < 1e-12


def test_batched_joints_and_float32():
    pose, joints = _random(B=2, seed=1)
    joints_b = joints.expand(2, -1, -1) + torch.randn(2, 1, 3, dtype=torch.float64)  # per-sample joints
    G, T = forward_kinematics(pose.float(), joints_b.float(), PARENTS)
    G_ref, T_ref = naive_fk(pose, joints_b, PARENTS)
    assert G.dtype == torch.float32
    assert (T.double() - T_ref).abs().max() < 1e-5


def test_identity_pose_gives_identity_skinning_transforms():
    _, joints = _random()
    pose = torch.zeros(4, len(PARENTS), 3)
    G, T = forward_kinematics(pose, joints.float(), PARENTS)
    assert torch.allclose(T, torch.eye(4).expand_as(T), atol=1e-6)
    assert torch.allclose(G[..., :3, 3], joints.float().expand(4, -1, -1), atol=1e-6)


def test_batch_consistency():
    pose, joints = _random(B=5, seed=2)
    _, T_all = forward_kinematics(pose, joints, PARENTS)
    for b in range(5):
        _, T_one = forward_kinematics(pose[b : b + 1], joints, PARENTS)
        assert torch.equal(T_one[0], T_all[b]) or (T_one[0] - T_all[b]).abs().max() < 1e-14


def test_rotmat_entry_point_matches_naive_loop():
    """Local rotation matrices from the matrix exponential (not our Rodrigues) give the naive loop's transforms."""
    pose, joints = _random(seed=4)
    rotations = torch.stack([torch.stack([_rodrigues64(aa) for aa in frame]) for frame in pose])  # [B, J, 3, 3]
    G, T = forward_kinematics_rotmat(rotations, joints, PARENTS)
    G_ref, T_ref = naive_fk(pose, joints, PARENTS)
    assert (G - G_ref).abs().max() < 1e-12
    assert (T - T_ref).abs().max() < 1e-12


@pytest.mark.parametrize("angle", [0.0, 1e-7, math.pi, 2 * math.pi - 1e-4])
def test_gradients_finite_at_extremes(angle):
    _, joints = _random(B=1, seed=3)
    pose = torch.zeros(2, len(PARENTS), 3, dtype=torch.float64)
    pose[:, :, 0] = angle
    pose[1, :, 1] = angle  # a second axis
    pose.requires_grad_(True)
    joints = joints.clone().requires_grad_(True)
    _, T = forward_kinematics(pose, joints, PARENTS)
    (T * torch.randn_like(T)).sum().backward()
    assert torch.isfinite(pose.grad).all() and torch.isfinite(joints.grad).all()
    _, T32 = forward_kinematics(pose.detach().float().requires_grad_(True), joints.detach().float(), PARENTS)
    assert torch.isfinite(T32).all()


def test_gradcheck_pose_and_joints():
    pose, joints = _random(B=2, seed=5)
    pose = (pose * 0.7).requires_grad_(True)
    joints = joints.requires_grad_(True)

    def fn(p, j):
        return forward_kinematics(p, j, PARENTS)[1][..., :3, :]

    assert torch.autograd.gradcheck(fn, (pose, joints), eps=1e-6, atol=1e-6)


def test_skin_points_matches_per_point_blend():
    pose, joints = _random(B=2, seed=6)
    _, T = forward_kinematics(pose, joints, PARENTS)
    g = torch.Generator().manual_seed(0)
    N, J = 50, len(PARENTS)
    pts = torch.randn(N, 3, generator=g, dtype=torch.float64)
    w = torch.rand(N, J, generator=g, dtype=torch.float64) ** 4
    w = w / w.sum(1, keepdim=True)
    out = skin_points(pts, w, T)  # [B, N, 3]
    ref = torch.zeros(2, N, 3, dtype=torch.float64)
    for b in range(2):
        for n in range(N):
            M = sum(w[n, k] * T[b, k] for k in range(J))
            ref[b, n] = (M @ torch.cat([pts[n], torch.ones(1, dtype=torch.float64)]))[:3]
    assert (out - ref).abs().max() < 1e-12
    # batched points and weights give the same result
    out_b = skin_points(pts.expand(2, -1, -1), w.expand(2, -1, -1), T)
    assert (out_b - out).abs().max() < 1e-13
    assert blend_transforms(w, T).shape == (2, N, 3, 4)
    # empty input
    assert skin_points(pts[:0], w[:0], T).shape == (2, 0, 3)


def test_rigid_root_rotation_rotates_everything():
    """Rotating only the root about its joint moves every skinned point rigidly (closed form)."""
    _, joints = _random(B=1, seed=7)
    pose = torch.zeros(1, len(PARENTS), 3, dtype=torch.float64)
    pose[0, 0] = torch.tensor([0.3, -1.1, 0.4], dtype=torch.float64)
    _, T = forward_kinematics(pose, joints, PARENTS)
    pts = torch.randn(20, 3, dtype=torch.float64)
    w = torch.softmax(torch.randn(20, len(PARENTS), dtype=torch.float64), dim=1)
    R = _rodrigues64(pose[0, 0])
    expected = (pts - joints[0]) @ R.T + joints[0]
    assert (skin_points(pts, w, T)[0] - expected).abs().max() < 1e-12


def test_parents_tensor_is_read_once_and_again_after_a_write(monkeypatch):
    """The parent table is read from its tensor once (on a GPU each read is a copy that waits for the device), and
    read again when the tensor is written to in place (a loaded checkpoint's buffer)."""
    pose, joints = _random()
    parents = torch.tensor(PARENTS)
    reads = []
    original = torch.Tensor.tolist
    monkeypatch.setattr(torch.Tensor, "tolist", lambda t: (t is parents and reads.append(1)) or original(t))
    for _ in range(3):
        G, _ = forward_kinematics(pose, joints, parents)
    assert len(reads) == 1
    torch.testing.assert_close(G, naive_fk(pose, joints, PARENTS)[0], atol=1e-12, rtol=0)
    other = [-1, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9]  # a chain: a different tree over the same joints
    parents.copy_(torch.tensor(other))
    G, _ = forward_kinematics(pose, joints, parents)
    assert len(reads) == 2
    torch.testing.assert_close(G, naive_fk(pose, joints, other)[0], atol=1e-12, rtol=0)
