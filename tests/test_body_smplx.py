"""The `smplx` body through smplx's real loading path, with an SMPL-X-format model file built from the procedural body.

The file holds SMPL-X's arrays (v_template, shapedirs with 10 shape + 10 expression components as in the v1.0 files,
posedirs, J_regressor, weights, kintree_table with SMPL-X's 55-joint tree, f, hand PCA bases and means, landmark
faces). smplx picks extra joints by fixed SMPL-X vertex ids (up to 9929), so the procedural mesh is padded to SMPL-X's
10475 vertices with surface samples. Fingers, jaw and eyes get real skinning weights, so their rotations move
vertices and the comparison with smplx's own forward covers them.
"""

from __future__ import annotations

import copy
import math
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch
from test_body_smpl import nearest_vertex_regressor, padded_procedural_mesh

from framework.errors import SplatrigError

smplx = pytest.importorskip("smplx")
from plugins.body.smplx_body import SMPLXBody, pose_input_indices  # noqa: E402

N_VERTS = 10475
J = 55
SMPLX_PARENTS = [
    -1,
    0,
    0,
    0,
    1,
    2,
    3,
    4,
    5,
    6,
    7,
    8,
    9,
    9,
    9,
    12,
    13,
    14,
    16,
    17,
    18,
    19,
    15,
    15,
    15,
    20,
    25,
    26,
    20,
    28,
    29,
    20,
    31,
    32,
    20,
    34,
    35,
    20,
    37,
    38,
    21,
    40,
    41,
    21,
    43,
    44,
    21,
    46,
    47,
    21,
    49,
    50,
    21,
    52,
    53,
]
# procedural joint -> the SMPL-X joint that takes its skinning weight
PROCEDURAL_TO_SMPLX = {
    "pelvis": 0,
    "spine": 3,
    "chest": 9,
    "neck": 12,
    "head": 15,
    "upperarm.L": 16,
    "lowerarm.L": 18,
    "hand.L": 20,
    "upperarm.R": 17,
    "lowerarm.R": 19,
    "hand.R": 21,
    "upperleg.L": 1,
    "lowerleg.L": 4,
    "foot.L": 7,
    "upperleg.R": 2,
    "lowerleg.R": 5,
    "foot.R": 8,
}


def smplx_joint_positions(rest_joints: dict[str, np.ndarray]) -> np.ndarray:
    """[55, 3] designed rest positions: the procedural joints where they exist, fingers fanned around each hand."""
    p = np.zeros((J, 3))
    for name, k in PROCEDURAL_TO_SMPLX.items():
        p[k] = rest_joints[name]
    p[6] = (0.0, 0.0, 0.19)  # spine2
    p[10], p[11] = rest_joints["foot.L"] + (0, -0.1, -0.02), rest_joints["foot.R"] + (0, -0.1, -0.02)
    p[13], p[14] = (0.08, 0.0, 0.44), (-0.08, 0.0, 0.44)  # collars
    p[22], p[23], p[24] = (0.0, -0.05, 0.64), (0.035, -0.09, 0.70), (-0.035, -0.09, 0.70)  # jaw, eyes
    for first, sign in ((25, 1.0), (40, -1.0)):
        for finger in range(5):
            a = 2 * math.pi * finger / 5
            for seg, x in enumerate((0.72, 0.75, 0.77)):
                p[first + 3 * finger + seg] = (sign * x, 0.02 * math.cos(a), 0.44 + 0.02 * math.sin(a))
    return p


def write_smplx_file(path: Path, seed: int = 0) -> dict[str, np.ndarray]:
    """An SMPL-X-format file (.npz or .pkl by the suffix of `path`); returns its arrays."""
    body, v, w17 = padded_procedural_mesh(N_VERTS, seed)
    rng = np.random.default_rng(seed)
    names = body.joint_names
    w = np.zeros((N_VERTS, J))
    for k, name in enumerate(names):
        w[:, PROCEDURAL_TO_SMPLX[name]] += w17[:, k]
    joints = smplx_joint_positions({n: body.rest_joints[k].double().numpy() for k, n in enumerate(names)})
    # hands beyond x = 0.71: half of the weight goes to the nearest finger joint; the face front to jaw and eyes
    for first, wrist, sign in ((25, 20, 1.0), (40, 21, -1.0)):
        sel = np.where(sign * v[:, 0] > 0.71)[0]
        near = first + np.argmin(np.linalg.norm(v[sel, None] - joints[None, first : first + 15], axis=-1), axis=1)
        moved = 0.5 * w[sel, wrist]
        w[sel, wrist] -= moved
        w[sel, near] += moved
    face = np.where((v[:, 1] < -0.04) & (v[:, 2] > 0.6))[0]
    near = 22 + np.argmin(np.linalg.norm(v[face, None] - joints[None, 22:25], axis=-1), axis=1)
    w[face, near] += 0.5 * w[face, 15]
    w[face, 15] *= 0.5
    shapedirs = np.zeros((N_VERTS, 3, 20))
    shapedirs[:, :, 0] = 0.05 * v  # beta 0: global size
    shapedirs[:, :, 1:10] = 0.01 * rng.standard_normal((N_VERTS, 3, 9))
    shapedirs[face, :, 10:] = 0.005 * rng.standard_normal((len(face), 3, 10))  # expression moves the face only
    kintree = np.stack([np.array(SMPLX_PARENTS), np.arange(J)]).astype(np.int64)
    kintree[0, 0] = 4294967295
    comps = [np.linalg.qr(rng.standard_normal((45, 45)))[0].T for _ in range(2)]  # orthonormal PCA bases
    data = {
        "v_template": v,
        "shapedirs": shapedirs,
        "posedirs": np.zeros((N_VERTS, 3, (J - 1) * 9), np.float32),
        "J_regressor": nearest_vertex_regressor(v, joints),
        "weights": w,
        "kintree_table": kintree,
        "f": body.faces.numpy().astype(np.uint32),
        "hands_componentsl": comps[0],
        "hands_componentsr": comps[1],
        "hands_meanl": 0.3 * rng.standard_normal(45),
        "hands_meanr": 0.3 * rng.standard_normal(45),
        "lmk_faces_idx": rng.integers(0, len(body.faces), 51),
        "lmk_bary_coords": np.full((51, 3), 1 / 3),
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix == ".npz":
        np.savez_compressed(path, **data)
    else:
        with open(path, "wb") as fh:
            pickle.dump(data, fh, protocol=2)
    return data


@pytest.fixture(scope="module")
def smplx_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("smplx") / "SMPLX_NEUTRAL.npz"
    write_smplx_file(path)
    return path


@pytest.fixture(scope="module")
def body(smplx_file: Path) -> SMPLXBody:
    return SMPLXBody(model_path=str(smplx_file))


def smplx_forward(path: Path, pose: torch.Tensor, betas: torch.Tensor, **kwargs) -> torch.Tensor:
    """smplx's own SMPL-X forward (float64) for full poses [B, 55, 3], or hand PCA coefficients via kwargs."""
    use_pca = "left_hand_pose" in kwargs
    model = smplx.SMPLX(
        model_path=str(path),
        ext=path.suffix[1:],
        num_betas=10,
        use_pca=use_pca,
        num_pca_comps=6,
        flat_hand_mean=True,
        dtype=torch.float64,
    )
    B = pose.shape[0]
    hands = {"left_hand_pose": pose[:, 25:40].reshape(B, -1), "right_hand_pose": pose[:, 40:55].reshape(B, -1)}
    hands.update(kwargs)
    with torch.no_grad():
        out = model(
            betas=betas.expand(B, -1),
            global_orient=pose[:, 0],
            body_pose=pose[:, 1:22].reshape(B, -1),
            jaw_pose=pose[:, 22],
            leye_pose=pose[:, 23],
            reye_pose=pose[:, 24],
            expression=torch.zeros(B, 10, dtype=torch.float64),
            transl=torch.zeros(B, 3, dtype=torch.float64),
            **hands,
        )
    return out.vertices


def test_posed_vertices_match_smplx_forward_with_hands_and_face(smplx_file: Path):
    betas = torch.tensor([0.8, -1.0, 0.5, 0, 0, 0, 0, 0, 0, 0.3], dtype=torch.float64)
    body = SMPLXBody(model_path=str(smplx_file.parent), betas=betas.tolist())  # the folder form of model_path
    assert body.num_joints == 55 and body.rest_vertices.shape == (N_VERTS, 3)
    assert body.parents.tolist() == SMPLX_PARENTS
    g = torch.Generator().manual_seed(3)
    pose = 0.5 * torch.randn(2, J, 3, generator=g, dtype=torch.float64)
    ref = smplx_forward(smplx_file, pose, betas)
    err = (body.posed_vertices(pose.float()).double() - ref).abs().max().item()
    assert err < 1e-5, err
    # fingers, jaw and eyes are real joints: rotating only them moves vertices (hands / face), and only those
    for joints in ([25, 26, 27, 40], [22, 23, 24]):
        only = torch.zeros(1, J, 3)
        only[0, joints] = 0.8
        moved = (body.posed_vertices(only)[0] - body.rest_vertices).norm(dim=-1)
        assert moved.max() > 5e-3 and (moved > 1e-6).float().mean() < 0.1


def test_joint_names_and_pose_input_choice(body: SMPLXBody):
    names = body.joint_names
    assert len(names) == 55 and names[:2] == ["pelvis", "left_hip"] and names[21] == "right_wrist"
    assert names[22] == "jaw" and names[25] == "left_index1" and names[54] == "right_thumb3"
    pose = torch.randn(3, J, 3)
    # default: the 22 body joints (66 values) feed F_a, fingers and eyes do not
    assert body.num_pose_features == 66
    torch.testing.assert_close(body.pose_features(pose), pose[:, :22].reshape(3, 66))
    full = copy.copy(body)
    full.pose_input_joints = pose_input_indices("all", names)
    assert full.num_pose_features == 165 and torch.equal(full.pose_features(pose), pose.reshape(3, 165))
    full.pose_input_joints = pose_input_indices(["pelvis", "jaw"], names)
    torch.testing.assert_close(full.pose_features(pose), pose[:, [0, 22]].reshape(3, 6))
    with pytest.raises(ValueError, match="unknown joint.*'nose'"):
        pose_input_indices(["pelvis", "nose"], names)
    with pytest.raises(ValueError, match="'body', 'all' or a list"):
        pose_input_indices("hands", names)


@pytest.mark.slow  # ~65 s on 2 cores: a whole SMPL-X avatar built and stepped; `pytest -m slow` runs it
def test_avatar_feeds_the_corrector_only_the_pose_input_joints(body: SMPLXBody):
    from framework.model.avatar import Avatar, GaussianParams
    from framework.model.gaussian_init import from_body_surface
    from framework.plugins import load_plugins
    from framework.registry import REGISTRIES
    from framework.types import Cameras, FrameBatch

    load_plugins()
    corrector = REGISTRIES["corrector"].build("latent")
    corrector.bind(body.num_pose_features)
    deformer = REGISTRIES["deformer"].build("lbs")
    deformer.bind(body, torch.tensor([[-1.0] * 3, [1.0] * 3]))
    g = from_body_surface(body, num=64, sh_degree=0, seed=0)
    avatar = Avatar(GaussianParams(g), REGISTRIES["rasterizer"].build("torch_ref"), corrector, deformer, body)
    pose = torch.randn(1, J, 3) * 0.3
    cams = Cameras(K=torch.eye(3)[None], world_to_cam=torch.eye(4)[None], width=4, height=4)
    batch = FrameBatch(
        image=torch.zeros(1, 4, 4, 3),
        mask=torch.zeros(1, 4, 4),
        boundary=torch.ones(1, 4, 4),
        cameras=cams,
        frame=torch.zeros(1, dtype=torch.long),
        pose=pose,
    )
    transforms, features = avatar.bone_transforms(batch)
    assert transforms.shape == (J, 4, 4) and features.shape == (66,)
    torch.testing.assert_close(features, pose[0, :22].reshape(-1))
    out = avatar.pose(batch)[1]
    assert torch.isfinite(out.means).all()


def test_pkl_file_and_gender_lookup(tmp_path: Path):
    write_smplx_file(tmp_path / "smplx" / "SMPLX_MALE.pkl", seed=1)
    body = SMPLXBody(model_path=str(tmp_path), gender="male")  # <folder>/smplx/SMPLX_MALE.pkl, as EasyMocap lays out
    assert body.model_file.endswith("SMPLX_MALE.pkl") and body.num_joints == 55


def test_missing_file_error_names_the_expected_files(tmp_path: Path):
    with pytest.raises(FileNotFoundError) as info:
        SMPLXBody(model_path=str(tmp_path / "models"))
    msg = str(info.value)
    assert isinstance(info.value, SplatrigError)  # entry points print it as one line, no traceback
    assert "SMPLX_NEUTRAL.npz" in msg and str(tmp_path / "models" / "SMPLX_NEUTRAL.pkl") in msg
    assert "smpl-x.is.tue.mpg.de" in msg and "body.model_path=" in msg
    with pytest.raises(FileNotFoundError, match="body.model_path is not set"):
        SMPLXBody(model_path=None)
