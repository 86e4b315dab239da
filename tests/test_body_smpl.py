"""The `smpl` body through smplx's real loading path, with an SMPL-format model file built from the procedural body.

The file is a pickle of plain numpy arrays in SMPL's layout (v_template, shapedirs, posedirs, J_regressor, weights,
kintree_table, f). smplx appends extra joints by fixed SMPL vertex ids (up to 6889), so the mesh is padded to SMPL's
6890 vertices with surface samples of the procedural body (extra points not referenced by faces, their skinning
weights interpolated from the triangle they lie on).
"""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch

from plugins.body.procedural import ProceduralBody
from plugins.body.smpl import SMPLBody, resolve_model_file

smplx = pytest.importorskip("smplx")
N_VERTS = 6890


def padded_procedural_mesh(num_vertices: int, seed: int = 0) -> tuple[ProceduralBody, np.ndarray, np.ndarray]:
    """The procedural body's rest vertices padded to `num_vertices` with surface samples (not referenced by faces),
    and skinning weights interpolated from the triangle each sample lies on: (body, v [V, 3], w [V, J]) float64."""
    body = ProceduralBody()
    V0 = body.rest_vertices.shape[0]
    pts, fid, bary = body.surface_samples(num_vertices - V0, seed=seed)
    w_extra = (bary.unsqueeze(-1) * body.skin_weights[body.faces[fid]]).sum(1)
    v = torch.cat([body.rest_vertices, pts]).double().numpy()
    w = torch.cat([body.skin_weights, w_extra]).double().numpy()
    return body, v, w


def nearest_vertex_regressor(v: np.ndarray, points: np.ndarray, k: int = 8) -> np.ndarray:
    """[len(points), V]: the mean of the k vertices nearest each point (a convex combination, like SMPL's)."""
    reg = np.zeros((len(points), len(v)))
    for row, p in enumerate(points):
        reg[row, np.argsort(np.linalg.norm(v - p, axis=1))[:k]] = 1.0 / k
    return reg


def write_smpl_file(path, posedirs_scale: float = 0.0, seed: int = 0) -> dict[str, np.ndarray]:
    body, v, w = padded_procedural_mesh(N_VERTS, seed)  # [6890, 3], [6890, J]
    J = body.num_joints
    rng = np.random.default_rng(seed)
    Jreg = nearest_vertex_regressor(v, body.rest_joints.double().numpy())
    shapedirs = np.zeros((N_VERTS, 3, 10))
    shapedirs[:, :, 0] = 0.05 * v  # beta 0: global size
    shapedirs[:, :, 1:] = 0.01 * rng.standard_normal((N_VERTS, 3, 9))
    posedirs = posedirs_scale * rng.standard_normal((N_VERTS, 3, (J - 1) * 9))
    kintree = np.stack([body.parents.numpy(), np.arange(J)]).astype(np.int64)
    kintree[0, 0] = 4294967295  # as in SMPL's files: the root's "parent" is uint32 -1
    data = {
        "v_template": v,
        "shapedirs": shapedirs,
        "posedirs": posedirs,
        "J_regressor": Jreg,
        "weights": w,
        "kintree_table": kintree,
        "f": body.faces.numpy().astype(np.uint32),
    }
    with open(path, "wb") as fh:
        pickle.dump(data, fh, protocol=2)
    return data


def smplx_vertices(path, pose: torch.Tensor, betas: torch.Tensor) -> torch.Tensor:
    model = smplx.SMPL(model_path=str(path), num_betas=10, dtype=torch.float64)
    B = pose.shape[0]
    with torch.no_grad():
        out = model(
            betas=betas.expand(B, -1),
            global_orient=pose[:, 0],
            body_pose=pose[:, 1:].reshape(B, -1),
            transl=torch.zeros(B, 3, dtype=torch.float64),
        )
    return out.vertices


def _pose(B: int, J: int, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return 0.7 * torch.randn(B, J, 3, generator=g, dtype=torch.float64)


def test_posed_vertices_match_smplx_forward(tmp_path):
    path = tmp_path / "SMPL_NEUTRAL.pkl"
    data = write_smpl_file(path, posedirs_scale=0.0)
    betas = torch.tensor([0.8, -1.0, 0.5, 0, 0, 0, 0, 0, 0, 0.3], dtype=torch.float64)
    body = SMPLBody(model_path=str(tmp_path), betas=betas.tolist())  # the folder form of model_path
    J = body.num_joints
    assert J == 17 and body.rest_vertices.shape == (N_VERTS, 3) and body.faces.shape[0] == len(data["f"])
    assert body.parents.tolist() == [-1] + data["kintree_table"][0, 1:].tolist()
    pose = _pose(3, J)
    ref = smplx_vertices(path, pose, betas)  # smplx's own forward, float64
    ours = body.posed_vertices(pose.float())
    err = (ours.double() - ref).abs().max().item()
    assert err < 1e-5, err
    # the rest joints are SMPL's regression of the shaped rest mesh (independently computed here)
    v_shaped = data["v_template"] + data["shapedirs"] @ betas.numpy()
    assert np.abs(body.rest_joints.double().numpy() - data["J_regressor"] @ v_shaped).max() < 1e-6
    # rest pose is the shaped template
    assert torch.allclose(body.posed_vertices(torch.zeros(1, J, 3))[0], body.rest_vertices, atol=1e-6)


def test_pose_blendshapes_effect(tmp_path):
    """With non-zero posedirs smplx's mesh includes pose correctives: `pose_blendshapes=True` reproduces it, the
    default (pure LBS, what Gaussians can follow) differs by exactly the skinned corrective offsets."""
    path = tmp_path / "SMPL_NEUTRAL.pkl"
    write_smpl_file(path, posedirs_scale=2e-3)
    betas = torch.zeros(10, dtype=torch.float64)
    pose = _pose(2, 17, seed=4)
    ref = smplx_vertices(path, pose, betas)
    with_pbs = SMPLBody(model_path=str(path), pose_blendshapes=True)
    err_on = (with_pbs.posed_vertices(pose.float()).double() - ref).abs().max().item()
    assert err_on < 1e-5, err_on
    lbs_only = SMPLBody(model_path=str(path))
    gap = (lbs_only.posed_vertices(pose.float()).double() - ref).abs().max().item()
    assert gap > 1e-3, gap  # visible: pure LBS does not include the correctives
    assert lbs_only.posedirs is None
    # the identity pose has no correctives: both agree there
    zero = torch.zeros(1, 17, 3)
    assert torch.allclose(with_pbs.posed_vertices(zero), lbs_only.posed_vertices(zero), atol=1e-6)


def test_bone_transforms_match_smplx_rigid_transform(tmp_path):
    from smplx.lbs import batch_rigid_transform

    path = tmp_path / "SMPL_NEUTRAL.pkl"
    write_smpl_file(path)
    body = SMPLBody(model_path=str(path)).double()
    pose = _pose(2, 17, seed=5)
    joints = body.rest_joints.expand(2, -1, -1)
    from framework.geometry import axis_angle_to_rotmat

    _, A = batch_rigid_transform(axis_angle_to_rotmat(pose), joints, body.parents, dtype=torch.float64)
    assert (body.bone_transforms(pose) - A).abs().max() < 1e-12


def test_missing_file_error_names_file_path_and_licensor(tmp_path):
    with pytest.raises(FileNotFoundError) as info:
        SMPLBody(model_path=str(tmp_path / "models"))
    msg = str(info.value)
    assert "SMPL_NEUTRAL.pkl" in msg
    assert str(tmp_path / "models" / "SMPL_NEUTRAL.pkl") in msg
    assert "smpl.is.tue.mpg.de" in msg and "licence forbids redistribution" in msg
    with pytest.raises(FileNotFoundError, match="SMPL_FEMALE.pkl"):
        resolve_model_file(None, "smpl", "female")
    with pytest.raises(FileNotFoundError, match="SMPLX_MALE.npz.*smpl-x.is.tue.mpg.de"):
        resolve_model_file(tmp_path, "smplx", "male")
    with pytest.raises(ValueError, match="gender"):
        resolve_model_file(tmp_path, "smpl", "other")


def test_wrong_pose_shape_is_explained(tmp_path):
    path = tmp_path / "SMPL_NEUTRAL.pkl"
    write_smpl_file(path)
    body = SMPLBody(model_path=str(path))
    with pytest.raises(ValueError, match=r"\[B, 17, 3\]"):
        body.bone_transforms(torch.zeros(1, 24, 3))
