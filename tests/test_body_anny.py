"""The `anny` body against Anny's own code.

Three levels, so the default run stays fast on a machine with empty caches:
- always: our FK + the pose conversion against Anny's kinematics module (`anny/utils/kinematics.py`, loaded by file
  path so the heavy `anny` package is not imported) on a random skeleton with random rest/reference orientations;
- with our cached asset (cheap to load; marked `slow` when it must be built first, ~1-1.5 min): the real 104-bone
  rig and mesh, our FK + LBS against Anny's kinematics and skinning functions;
- with Anny's own cache (marked `slow` when absent): Anny's full forward `Anny()(pose_parameters=...)`.
Set SPLATRIG_CACHE_DIR / ANNY_CACHE_DIR to persistent folders to keep the assets between CI runs.
"""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from framework.geometry import axis_angle_to_rotmat
from framework.rig.kinematics import forward_kinematics, skin_points
from plugins.body.anny_body import (
    PHENOTYPE_DEFAULTS,
    REDUCED_JOINTS,
    AnnyBody,
    anny_pose_parameters,
    asset_path,
    fold_skeleton,
)

pytest.importorskip("roma")


def _anny_file_module(relpath: str, name: str):
    spec = importlib.util.find_spec("anny")
    if spec is None or not spec.submodule_search_locations:
        pytest.skip("anny is not installed")
    path = Path(spec.submodule_search_locations[0]) / relpath
    mod_spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(mod_spec)
    mod_spec.loader.exec_module(module)
    return module


def _anny_cache_ready() -> bool:
    root = Path(os.environ.get("ANNY_CACHE_DIR", Path.home() / ".cache" / "anny"))
    return any(root.glob("*/build_compact_model_data_*.safetensors"))


ASSET_READY = asset_path(dict(PHENOTYPE_DEFAULTS)).exists()


def _no_mark(f):
    return f


slow_unless_asset = pytest.mark.slow if not ASSET_READY else _no_mark
slow_unless_anny_cache = pytest.mark.slow if not (_anny_cache_ready() and ASSET_READY) else _no_mark


def _random_rotations(n: int, gen: torch.Generator) -> torch.Tensor:
    q = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        -1,
    ).reshape(n, 3, 3)


def test_pose_conversion_matches_anny_kinematics_on_random_rig():
    """Fast, no cache: Anny's `local-ref` FK with converted deltas equals our FK, for arbitrary rest and reference
    orientations (Anny's reference orientations differ from the rest ones) and a non-trivial root."""
    kin = _anny_file_module("utils/kinematics.py", "_anny_kinematics_probe")
    gen = torch.Generator().manual_seed(3)
    parents = [-1, 0, 1, 2, 1, 4, 5, 0, 7, 8, 0, 10, 11, 12, 11]
    J, B = len(parents), 4
    heads = torch.randn(J, 3, generator=gen, dtype=torch.float64) * 0.3
    R = _random_rotations(J, gen)
    U = R @ axis_angle_to_rotmat(0.1 * torch.randn(J, 3, generator=gen, dtype=torch.float64))  # reference
    U[0] = R[0]  # Anny's root: reference = rest orientation (its children are offset in the rest frame)
    rest = torch.eye(4, dtype=torch.float64).repeat(J, 1, 1)
    rest[:, :3, :3], rest[:, :3, 3] = R, heads
    pose = torch.randn(B, J, 3, generator=gen, dtype=torch.float64)
    pose[0] = 0.0
    pose[1, 3] = torch.tensor([torch.pi, 0.0, 0.0], dtype=torch.float64)  # half turn
    delta = anny_pose_parameters(pose, rest, U, heads, parents)
    chain = kin.get_kinematic_chain(parents)
    T_anny, _ = kin.forward_kinematic(chain, rest.expand(B, J, 4, 4), delta, "local-ref", U)
    _, T_ours = forward_kinematics(pose, heads, torch.tensor(parents))
    err = (T_ours - T_anny).abs().max().item()
    assert err < 1e-12, err
    assert torch.allclose(T_ours[0], torch.eye(4, dtype=torch.float64).expand(J, 4, 4), atol=1e-14)
    # the naive conversion (delta = R(θ), ignoring reference orientations) must NOT match: the test has teeth
    naive = delta.clone()
    naive[:, 1:, :3, :3] = axis_angle_to_rotmat(pose[:, 1:])
    T_naive, _ = kin.forward_kinematic(chain, rest.expand(B, J, 4, 4), naive, "local-ref", U)
    assert (T_naive - T_ours).abs().max() > 1e-3


@pytest.fixture(scope="session")
def anny_full() -> AnnyBody:
    return AnnyBody(skeleton="full")  # builds the asset on first use (~1-1.5 min with empty caches)


@pytest.fixture(scope="session")
def anny_reduced() -> AnnyBody:
    return AnnyBody(skeleton="reduced")


@slow_unless_asset
def test_asset_fk_matches_anny_kinematics_full_rig(anny_full):
    """Real rig (104 bones) and mesh: our FK + LBS vs Anny's own kinematics and dense skinning, float64."""
    from plugins.body.anny_body import load_anny_asset

    kin = _anny_file_module("utils/kinematics.py", "_anny_kinematics_probe")
    skin = _anny_file_module("skinning/skinning.py", "_anny_skinning_probe")
    a = {k: torch.as_tensor(v) for k, v in load_anny_asset().items() if k not in ("bone_labels", "meta")}
    parents = a["parents"].tolist()
    gen = torch.Generator().manual_seed(0)
    B, J = 3, len(parents)
    pose = 0.6 * torch.randn(B, J, 3, generator=gen, dtype=torch.float64)
    delta = anny_pose_parameters(pose, a["rest_bone_poses"], a["reference_orientations"], a["rest_joints"], parents)
    chain = kin.get_kinematic_chain(parents)
    T_anny, _ = kin.forward_kinematic(
        chain, a["rest_bone_poses"].expand(B, J, 4, 4), delta, "local-ref", a["reference_orientations"]
    )
    W = skin.dense_bone_weights(a["bone_weights"], a["bone_indices"].long(), J)
    v_anny = skin.dense_linear_blend_skinning(a["rest_vertices"].expand(B, -1, -1), W, T_anny)
    _, T_ours = forward_kinematics(pose, a["rest_joints"], a["parents"])
    v_ours = skin_points(a["rest_vertices"], W, T_ours)
    err64 = (v_ours - v_anny).abs().max().item()
    assert err64 < 1e-10, err64
    # the registered body (float32 buffers) against the float64 reference
    v_body = anny_full.posed_vertices(pose.float())
    err32 = (v_body.double() - v_anny).abs().max().item()
    assert err32 < 1e-5, err32


@slow_unless_anny_cache
def test_posed_vertices_match_anny_forward(anny_full, anny_reduced):
    """Anny's complete forward pass (its own rest model, FK and Warp skinning) vs our body, full and reduced rig."""
    import anny

    model = anny.Anny()
    a_rest = model()  # identity deltas
    gen = torch.Generator().manual_seed(1)
    B, J = 3, anny_full.num_joints
    pose = 0.6 * torch.randn(B, J, 3, generator=gen, dtype=torch.float64)
    rest_poses = a_rest["rest_bone_poses"][0]
    delta = anny_pose_parameters(
        pose, rest_poses, model.reference_bone_orientations, a_rest["rest_bone_heads"][0], model.bone_parents
    )
    with torch.no_grad():
        ref = model(pose_parameters=delta)["vertices"]  # [B, V, 3] float64
    # float64 through our FK + LBS on the asset's float64 arrays (the body's buffers are float32)
    from plugins.body.anny_body import load_anny_asset

    a = load_anny_asset()
    rest_v, joints = torch.as_tensor(a["rest_vertices"]), torch.as_tensor(a["rest_joints"])
    W = torch.zeros(rest_v.shape[0], J, dtype=torch.float64)
    W.scatter_add_(1, torch.as_tensor(a["bone_indices"]).long(), torch.as_tensor(a["bone_weights"]))
    _, T = forward_kinematics(pose, joints, torch.as_tensor(a["parents"]))
    err64 = (skin_points(rest_v, W, T) - ref).abs().max().item()
    err32 = (anny_full.posed_vertices(pose.float()).double() - ref).abs().max().item()
    assert err64 < 1e-10, err64
    assert err32 < 1e-5, err32
    # reduced skeleton: folded bones at identity reproduce Anny's output too
    red_pose = pose[:, anny_reduced.kept_full_indices]
    with torch.no_grad():
        ref_red = model(
            pose_parameters=anny_pose_parameters(
                anny_reduced.full_pose(red_pose),
                rest_poses,
                model.reference_bone_orientations,
                a_rest["rest_bone_heads"][0],
                model.bone_parents,
            )
        )
    err_red = (anny_reduced.posed_vertices(red_pose.float()).double() - ref_red["vertices"]).abs().max().item()
    assert err_red < 1e-5, err_red
    print(f"anny forward vs ours: float64 {err64:.2e}, float32 {err32:.2e}, reduced float32 {err_red:.2e}")


@slow_unless_asset
def test_reduced_equals_full_with_folded_identity(anny_full, anny_reduced):
    assert anny_reduced.joint_names == list(REDUCED_JOINTS)
    assert anny_reduced.num_joints == 22 and anny_full.num_joints == 104
    gen = torch.Generator().manual_seed(2)
    pose = 0.5 * torch.randn(2, anny_reduced.num_joints, 3, generator=gen)
    v_red = anny_reduced.posed_vertices(pose)
    v_full = anny_full.posed_vertices(anny_reduced.full_pose(pose))
    assert (v_red - v_full).abs().max() < 1e-5
    # folding conserves every vertex's weight mass; a finger rotation moves the full body but not the reduced one
    assert torch.allclose(anny_reduced.skin_weights.sum(1), torch.ones(anny_reduced.rest_vertices.shape[0]), atol=1e-5)
    full_pose = anny_reduced.full_pose(pose)
    full_pose[:, anny_full.joint_names.index("finger2-2.L")] = torch.tensor([0.0, 0.0, 1.0])
    assert (anny_full.posed_vertices(full_pose) - v_full).abs().max() > 1e-3


def test_fold_skeleton_maps_to_nearest_kept_ancestor():
    labels = ["root", "a", "a_twist", "b", "b_tip", "c"]
    parents = [-1, 0, 1, 2, 3, 0]
    kept, red_parents, to_red = fold_skeleton(labels, parents, ("root", "a", "b"))
    assert kept == [0, 1, 3]
    assert red_parents == [-1, 0, 1]
    assert to_red == [0, 1, 1, 2, 2, 0]
    with pytest.raises(ValueError, match="not in the rig"):
        fold_skeleton(labels, parents, ("root", "zz"))


@slow_unless_asset
def test_body_buffers_and_surface(anny_reduced):
    b = anny_reduced
    V, F = b.rest_vertices.shape[0], b.faces.shape[0]
    assert (V, F) == (13718, 27420)
    assert b.rest_vertices.dtype == torch.float32 and b.skin_weights.shape == (V, 22)
    z = b.rest_vertices[:, 2]
    assert 1.5 < float(z.max() - z.min()) < 1.8  # ~1.63 m, Z up
    assert b.uvs.shape[1] == 2 and b.face_uvs.shape == (F, 3)
    assert int(b.face_uvs.max()) < b.uvs.shape[0] and float(b.uvs.min()) >= 0 and float(b.uvs.max()) <= 1
    T = b.bone_transforms(torch.zeros(1, 22, 3))
    assert torch.allclose(T, torch.eye(4).expand_as(T), atol=1e-6)
    pts, fid, bary = b.surface_samples(2000, seed=0)
    pts2, _, _ = b.surface_samples(2000, seed=0)
    assert torch.equal(pts, pts2)
    corners = b.rest_vertices[b.faces[fid]]
    assert torch.allclose((bary.unsqueeze(-1) * corners).sum(1), pts, atol=1e-6)
    n = b.vertex_normals()
    # outward orientation: positive enclosed volume (an adult is ~0.06-0.08 m^3) and extreme vertices' normals
    v, f = b.rest_vertices.double(), b.faces
    volume = (v[f[:, 0]] * torch.linalg.cross(v[f[:, 1]], v[f[:, 2]], dim=-1)).sum() / 6
    assert 0.04 < float(volume) < 0.12, float(volume)
    assert n[int(z.argmax()), 2] > 0.9 and n[int(b.rest_vertices[:, 0].argmax()), 0] > 0.5
    with pytest.raises(ValueError, match="22 joints"):
        b.bone_transforms(torch.zeros(1, 104, 3))


@slow_unless_asset
def test_cached_asset_loads_without_importing_anny():
    code = (
        "import sys; from plugins.body.anny_body import AnnyBody; b = AnnyBody(); "
        "assert 'anny' not in sys.modules, 'anny was imported'; print(b.num_joints)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "22"


def test_bad_phenotype_and_skeleton_are_rejected():
    with pytest.raises(ValueError, match="outside"):
        AnnyBody(age=1.5)
    with pytest.raises(ValueError, match="'reduced' or 'full'"):
        AnnyBody(skeleton="tiny")


@pytest.mark.slow
def test_cold_build_prints_progress_and_writes_asset(tmp_path, monkeypatch, capfd):
    """Builds the asset into an empty project cache (Anny's own cache is reused if present)."""
    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(tmp_path))
    body = AnnyBody(skeleton="reduced", height=0.7)
    err = capfd.readouterr().err
    assert "building the Anny body asset once" in err
    assert list((tmp_path / "bodies").glob("anny-*.npz"))
    taller = body.rest_vertices[:, 2].max() - body.rest_vertices[:, 2].min()
    default = AnnyBody()
    assert taller > default.rest_vertices[:, 2].max() - default.rest_vertices[:, 2].min()
