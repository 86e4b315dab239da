"""The procedural capsule body: geometry, weights, posing, sampling."""

from __future__ import annotations

import torch

from framework.registry import BODIES
from plugins.body.procedural import ProceduralBody, capsule_mesh


def test_registered_and_deterministic():
    from framework.plugins import load_plugins

    load_plugins()
    a = BODIES.build("procedural")
    b = ProceduralBody()
    assert torch.equal(a.rest_vertices, b.rest_vertices) and torch.equal(a.skin_weights, b.skin_weights)
    assert a.rest_vertices.dtype == torch.float32 and a.faces.dtype == torch.long
    assert a.num_joints == len(a.joint_names) == 17
    assert {"rest_vertices", "faces", "skin_weights", "parents", "rest_joints", "uvs", "face_uvs"} <= set(
        dict(a.named_buffers())
    )


def test_shape_size_and_orientation():
    body = ProceduralBody()
    v, f = body.rest_vertices.double(), body.faces
    assert 1000 < v.shape[0] < 5000
    height = v[:, 2].max() - v[:, 2].min()
    assert 1.55 < height < 1.7  # Z up, ~1.6 m
    assert abs(float(v[:, 2].mean())) < 0.2
    # every capsule is closed and outward: positive signed volume, close to the sum of capsule volumes
    volume = (v[f[:, 0]] * torch.linalg.cross(v[f[:, 1]], v[f[:, 2]], dim=-1)).sum() / 6
    assert 0.04 < float(volume) < 0.1
    n = body.vertex_normals()
    top = int(v[:, 2].argmax())
    assert n[top, 2] > 0.9


def test_capsule_is_closed_and_outward():
    import numpy as np

    V, F = capsule_mesh(np.zeros(3), np.array([0.0, 0.0, 1.0]), 0.1, segments=24, cap_rings=8, ring_spacing=0.02)
    V = torch.as_tensor(V)
    F = torch.as_tensor(F)
    volume = (V[F[:, 0]] * torch.linalg.cross(V[F[:, 1]], V[F[:, 2]], dim=-1)).sum() / 6
    exact = torch.pi * 0.1**2 * 1.0 + 4 / 3 * torch.pi * 0.1**3
    assert abs(float(volume) / exact - 1) < 0.03  # polygonal approximation of the capsule
    edges = torch.cat([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    # closed and consistently oriented: every directed edge appears once and its reverse once
    fwd = {tuple(e) for e in edges.tolist()}
    assert len(fwd) == len(edges) and all((b, a) in fwd for a, b in fwd)


def test_weights_partition_of_unity_and_locality():
    body = ProceduralBody()
    w = body.skin_weights
    assert torch.allclose(w.sum(1), torch.ones(w.shape[0]), atol=1e-6)
    assert (w >= 0).all()
    # a hand-tip vertex belongs to the hand; a mid-thigh vertex to the upper leg
    v = body.rest_vertices
    names = body.joint_names
    tip = int(v[:, 0].argmax())
    assert w[tip, names.index("hand.L")] > 0.99
    thigh = int(((v - torch.tensor([0.16, 0.0, -0.24])).norm(dim=1)).argmin())
    assert w[thigh, names.index("upperleg.L")] > 0.9
    # blends exist near joints (smooth weights)
    assert ((w > 0.1).sum(1) >= 2).sum() > 100


def test_elbow_bend_moves_forearm_only():
    body = ProceduralBody()
    J = body.num_joints
    pose = torch.zeros(1, J, 3)
    pose[0, body.joint_names.index("lowerarm.L"), 2] = torch.pi / 2  # bend the left elbow about z
    posed = body.posed_vertices(pose)[0]
    moved = (posed - body.rest_vertices).norm(dim=1)
    w = body.skin_weights
    forearm = (w[:, body.joint_names.index("lowerarm.L")] + w[:, body.joint_names.index("hand.L")]) > 0.99
    torso = w[:, body.joint_names.index("chest")] > 0.99
    assert moved[torso].max() < 1e-6
    # the hand tip rotates 90 degrees about the elbow: from +x to +y of the elbow
    elbow = body.rest_joints[body.joint_names.index("lowerarm.L")]
    tip = int(body.rest_vertices[:, 0].argmax())
    expected = (
        elbow
        + torch.tensor([0.0, body.rest_vertices[tip, 0] - elbow[0], 0.0])
        + torch.tensor([-(body.rest_vertices[tip, 1] - elbow[1]), 0.0, body.rest_vertices[tip, 2] - elbow[2]])
    )
    assert (posed[tip] - expected).abs().max() < 1e-5
    assert moved[forearm].min() > 0.01


def test_bone_transforms_use_given_joints_and_check_shapes():
    """The body's transforms equal the naive float64 per-joint loop of test_kinematics, with the joints given."""
    from test_kinematics import naive_fk

    body = ProceduralBody()
    pose = torch.randn(2, body.num_joints, 3) * 0.3
    joints = body.rest_joints + 0.01
    T = body.bone_transforms(pose, joints)
    _, T_ref = naive_fk(pose.double(), joints.double(), body.parents.tolist())
    assert (T.double() - T_ref).abs().max() < 1e-5
    _, T_rest = naive_fk(pose.double(), body.rest_joints.double(), body.parents.tolist())
    assert (T_rest - T_ref).abs().max() > 1e-3  # the given joints matter
    import pytest

    with pytest.raises(ValueError, match="17, 3"):
        body.bone_transforms(torch.zeros(2, 16, 3))


def test_surface_samples_area_weighted_and_on_mesh():
    body = ProceduralBody()
    pts, fid, bary = body.surface_samples(20000, seed=7)
    assert pts.shape == (20000, 3) and fid.shape == (20000,) and bary.shape == (20000, 3)
    assert (bary >= 0).all() and torch.allclose(bary.sum(1), torch.ones(20000), atol=1e-6)
    corners = body.rest_vertices[body.faces[fid]]
    assert torch.allclose((bary.unsqueeze(-1) * corners).sum(1), pts, atol=1e-6)
    # area weighting: the fraction of samples on the head capsule matches its area fraction
    v, f = body.rest_vertices.double(), body.faces
    area = 0.5 * torch.linalg.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]], dim=-1).norm(dim=1)
    head = body.skin_weights[f[:, 0], body.joint_names.index("head")] > 0.99
    expected = float(area[head].sum() / area.sum())
    observed = float(head[fid].double().mean())
    assert abs(observed - expected) < 4 * (expected * (1 - expected) / 20000) ** 0.5 + 1e-3
    assert not torch.equal(pts, body.surface_samples(20000, seed=8)[0])
    assert torch.equal(pts, body.surface_samples(20000, seed=7)[0])
    empty = body.surface_samples(0)
    assert empty[0].shape == (0, 3)


def test_uvs_in_unit_square():
    body = ProceduralBody()
    assert body.uvs.shape == (body.rest_vertices.shape[0], 2)
    assert float(body.uvs.min()) >= 0.0 and float(body.uvs.max()) <= 1.0
    assert torch.equal(body.face_uvs, body.faces)
