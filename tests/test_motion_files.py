"""Motion files drive the avatar: BVH and AMASS-layout files retargeted by the documented joint mapping, our own pose
files read back, frame-rate resampling, and `python -m framework.render motion=FILE` end to end."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from trained_avatar import load_tiny

from framework.data.motion_files import Motion, read_motion_file, resample
from framework.data.motion_files.bvh import read_bvh
from framework.data.motion_files.smpl_skeleton import SCHEMATIC_REST, SMPL_JOINT_NAMES, SMPL_PARENTS
from framework.data.motions import Rig
from framework.data.zju.layout import save_pickled_dict
from framework.errors import SplatrigError
from framework.rig.kinematics import forward_kinematics
from plugins.body.procedural import JOINTS

# A CMU-style skeleton (Y up, centimetres, T-pose, facing +Z): (name, parent, offset)
BVH_JOINTS = [
    ("Hips", None, (0, 90, 0)),
    ("Spine", "Hips", (0, 10, 0)),
    ("Spine1", "Spine", (0, 20, 0)),
    ("Neck", "Spine1", (0, 20, 0)),
    ("Head", "Neck", (0, 10, 0)),
    ("LeftShoulder", "Spine1", (5, 15, 0)),
    ("LeftArm", "LeftShoulder", (12, 0, 0)),
    ("LeftForeArm", "LeftArm", (28, 0, 0)),
    ("LeftHand", "LeftForeArm", (25, 0, 0)),
    ("RightShoulder", "Spine1", (-5, 15, 0)),
    ("RightArm", "RightShoulder", (-12, 0, 0)),
    ("RightForeArm", "RightArm", (-28, 0, 0)),
    ("RightHand", "RightForeArm", (-25, 0, 0)),
    ("LeftUpLeg", "Hips", (9, -5, 0)),
    ("LeftLeg", "LeftUpLeg", (0, -40, 0)),
    ("LeftFoot", "LeftLeg", (0, -40, 0)),
    ("RightUpLeg", "Hips", (-9, -5, 0)),
    ("RightLeg", "RightUpLeg", (0, -40, 0)),
    ("RightFoot", "RightLeg", (0, -40, 0)),
]


def write_bvh(
    path: Path,
    frames: list[dict[str, tuple[float, float, float]]],
    frame_time: float,
    root_positions: list[tuple[float, float, float]] | None = None,
    order: str = "ZXY",
) -> Path:
    """A BVH file of BVH_JOINTS; frames[i][joint] = Euler angles in degrees, in `order` (default: 0)."""
    lines = ["HIERARCHY"]

    def emit(name: str, depth: int) -> None:
        pad = "  " * depth
        parent = next(p for n, p, _ in BVH_JOINTS if n == name)
        offset = next(o for n, _, o in BVH_JOINTS if n == name)
        lines.append(f"{pad}{'ROOT' if parent is None else 'JOINT'} {name}")
        lines.append(pad + "{")
        lines.append(f"{pad}  OFFSET {offset[0]} {offset[1]} {offset[2]}")
        rot = " ".join(f"{a}rotation" for a in order)
        lines.append(f"{pad}  CHANNELS {'6 Xposition Yposition Zposition ' if parent is None else '3 '}{rot}")
        children = [n for n, p, _ in BVH_JOINTS if p == name]
        for child in children:
            emit(child, depth + 1)
        if not children:
            lines.extend([f"{pad}  End Site", pad + "  {", f"{pad}    OFFSET 0 5 0", pad + "  }"])
        lines.append(pad + "}")

    emit("Hips", 0)
    lines += ["MOTION", f"Frames: {len(frames)}", f"Frame Time: {frame_time}"]
    depth_first = [line.split()[-1] for line in lines if line.strip().startswith(("ROOT", "JOINT"))]
    for i, angles in enumerate(frames):
        values = list(root_positions[i] if root_positions else (0, 90, 0))
        for name in depth_first:
            values += list(angles.get(name, (0.0, 0.0, 0.0)))
        lines.append(" ".join(f"{v:.6f}" for v in values))
    path.write_text("\n".join(lines) + "\n")
    return path


def procedural_rig(arm_drop_deg: float = 0.0) -> Rig:
    """The procedural body's skeleton (Z up, facing -y, T-pose), optionally with its arms lowered into an A-pose."""
    names = [n for n, _, _ in JOINTS]
    rest = np.array([j for _, _, j in JOINTS], dtype=np.float64)
    if arm_drop_deg:
        for side, sign in (("L", 1.0), ("R", -1.0)):
            shoulder = rest[names.index(f"upperarm.{side}")]
            R = Rotation.from_rotvec([0.0, sign * np.radians(arm_drop_deg), 0.0]).as_matrix()  # arm down
            for part in ("lowerarm", "hand"):
                k = names.index(f"{part}.{side}")
                rest[k] = shoulder + R @ (rest[k] - shoulder)
    return Rig(names, np.array([p for _, p, _ in JOINTS]), rest)


def posed_joints(rig: Rig, motion: Motion, frame: int) -> np.ndarray:
    """World joint positions [J, 3] of the rig posed by the motion's frame (our forward kinematics + root)."""
    G, _ = forward_kinematics(
        torch.tensor(motion.poses[frame : frame + 1], dtype=torch.float64),
        torch.tensor(rig.rest_joints),
        rig.parents.tolist(),
    )
    root = np.eye(4) if motion.roots is None else motion.roots[frame].astype(np.float64)
    return (root[:3, :3] @ G[0, :, :3, 3].numpy().T).T + root[:3, 3]


def bone(rig: Rig, joints: np.ndarray, a: str, b: str) -> np.ndarray:
    d = joints[rig.joint_names.index(b)] - joints[rig.joint_names.index(a)]
    return d / np.linalg.norm(d)


def test_bvh_euler_channels_follow_their_listed_order(tmp_path):
    """Channels `Zrotation Xrotation Yrotation` are intrinsic rotations in that order (R = Rz Rx Ry)."""
    angles = (30.0, -40.0, 75.0)
    path = write_bvh(tmp_path / "order.bvh", [{"Hips": angles, "LeftArm": (10.0, 20.0, 30.0)}], 1 / 30)
    src = read_bvh(path)
    expected = Rotation.from_euler("ZXY", angles, degrees=True).as_matrix()
    assert np.allclose(src.global_rotations[0, 0], expected, atol=1e-6)
    arm = src.joint_names.index("LeftArm")  # world rotation = hips * (shoulder = I) * arm
    assert np.allclose(
        src.global_rotations[0, arm],
        expected @ Rotation.from_euler("ZXY", (10, 20, 30), degrees=True).as_matrix(),
        atol=1e-6,
    )
    assert src.fps == pytest.approx(30.0)
    assert src.semantic["LeftArm"] == "shoulder.L" and src.semantic["Spine1"] == "chest"


@pytest.mark.parametrize("arm_drop_deg", [0.0, 45.0])
def test_bvh_that_raises_the_left_arm_raises_the_avatars_left_arm(tmp_path, arm_drop_deg):
    """Frame 1 turns LeftArm by +80 deg about the BVH's Z (its forward axis): the arm swings from +X (the subject's
    left) up to Y. On the avatar (left = +x, up = +z) the upper arm must point (cos 80, 0, sin 80), whatever its rest
    pose (T-pose, or an A-pose whose arms the rest-pose correction lifts), while the right arm stays level."""
    path = write_bvh(tmp_path / "raise.bvh", [{}, {"LeftArm": (80.0, 0.0, 0.0)}], 0.5)
    rig = procedural_rig(arm_drop_deg)
    motion = read_motion_file(path, rig, rig.num_joints)
    assert motion.poses.shape == (2, 17, 3) and motion.fps == pytest.approx(2.0)
    rest, raised = posed_joints(rig, motion, 0), posed_joints(rig, motion, 1)
    for joints in (rest, raised):  # the right arm is level in both frames (the source is a T-pose)
        assert np.allclose(bone(rig, joints, "upperarm.R", "lowerarm.R"), [-1, 0, 0], atol=1e-6)
        assert np.allclose(bone(rig, joints, "upperleg.L", "lowerleg.L"), [0, 0, -1], atol=1e-6)
    assert np.allclose(bone(rig, rest, "upperarm.L", "lowerarm.L"), [1, 0, 0], atol=1e-6)
    up = [np.cos(np.radians(80)), 0.0, np.sin(np.radians(80))]
    assert np.allclose(bone(rig, raised, "upperarm.L", "lowerarm.L"), up, atol=1e-6)
    assert np.allclose(bone(rig, raised, "lowerarm.L", "hand.L"), up, atol=1e-6)


def test_bvh_root_motion_is_placed_at_the_reference_and_scaled_to_the_avatar(tmp_path):
    """The hips walk 50 cm along the BVH's +Z (forward) while the whole body turns 90 deg about Y (up). With a
    reference root facing +x at (1, 2, 0), frame 0 stands there facing +x, and the pelvis moves forward by
    50 cm x (avatar leg / BVH leg), turned into the reference heading."""
    frames = [{}, {"Hips": (0.0, 0.0, 90.0)}]  # ZXY: the third angle is about Y
    path = write_bvh(tmp_path / "walk.bvh", frames, 0.1, root_positions=[(0, 90, 0), (0, 90, 50)])
    rig = procedural_rig()
    reference = np.eye(4)
    reference[:3, :3] = Rotation.from_rotvec([0, 0, np.pi / 2]).as_matrix()  # canonical forward -y turns to +x
    reference[:3, 3] = (1.0, 2.0, 0.0)
    motion = read_motion_file(path, rig, rig.num_joints, reference)
    j0 = posed_joints(rig, motion, 0)
    pelvis0 = reference[:3, :3] @ rig.rest_joints[0] + reference[:3, 3]
    assert np.allclose(j0[0], pelvis0, atol=1e-6)
    assert np.allclose(bone(rig, j0, "upperleg.R", "upperleg.L"), reference[:3, :3] @ [1, 0, 0], atol=1e-6)
    j1 = posed_joints(rig, motion, 1)
    leg_ratio = (0.36 + 0.34) / 80.0  # procedural hip-knee-ankle over the BVH's 40 + 40 cm
    assert np.allclose(j1[0] - j0[0], [50 * leg_ratio, 0, 0], atol=1e-6)
    # turning 90 deg left about up: the subject's left (+y after the reference turn) now points backwards (-x)
    assert np.allclose(bone(rig, j1, "upperleg.R", "upperleg.L"), [-1, 0, 0], atol=1e-6)
    assert np.allclose(motion.poses[:, 0], 0, atol=1e-6)  # the heading lives in the root transform, no tilt


def amass_file(path: Path, poses: np.ndarray, trans: np.ndarray, fps: float = 120.0) -> Path:
    np.savez(path, poses=poses, trans=trans, betas=np.zeros(16), gender=np.array("neutral"), mocap_framerate=fps)
    return path


def smplh_poses(num: int) -> np.ndarray:
    """[F, 156] SMPL-H poses: AMASS's usual global orientation Rx(+90 deg) (SMPL's Y up -> the world's Z up)."""
    poses = np.zeros((num, 52 * 3))
    poses[:, :3] = [np.pi / 2, 0, 0]
    return poses


def test_amass_left_shoulder_raises_the_avatars_left_arm(tmp_path):
    poses = smplh_poses(2)
    poses[1, 16 * 3 : 16 * 3 + 3] = [0, 0, np.radians(70)]  # left_shoulder about SMPL's z: +x (left) towards +y (up)
    trans = np.array([[0.3, -0.2, 0.9], [0.5, -0.2, 0.9]])
    path = amass_file(tmp_path / "amass.npz", poses, trans)
    rig = procedural_rig(45.0)
    motion = read_motion_file(path, rig, rig.num_joints)
    assert motion.fps == pytest.approx(120.0)
    rest, raised = posed_joints(rig, motion, 0), posed_joints(rig, motion, 1)
    # each avatar bone points where the SMPL bone points: AMASS's Rx(90) * the shoulder's Rz(70) * the rest bone
    assert np.allclose(
        bone(rig, rest, "upperarm.L", "lowerarm.L"), _smpl_world_dir("left_shoulder", "left_elbow"), atol=1e-6
    )
    raised_dir = _smpl_world_dir("left_shoulder", "left_elbow", Rotation.from_rotvec([0, 0, np.radians(70)]))
    assert np.allclose(bone(rig, raised, "upperarm.L", "lowerarm.L"), raised_dir, atol=1e-6)
    assert raised_dir[2] > 0.9  # i.e. up
    assert np.allclose(bone(rig, raised, "upperarm.R", "lowerarm.R"), bone(rig, rest, "upperarm.R", "lowerarm.R"))
    ratio = (0.36 + 0.34) / _smpl_leg()
    assert np.allclose(raised[0] - rest[0], [0.2 * ratio, 0, 0], atol=1e-6)  # AMASS faces -y here, as the avatar


def _smpl_world_dir(a: str, b: str, local: Rotation | None = None) -> np.ndarray:
    """World direction of SMPL bone a -> b of the schematic T-pose under AMASS's global orientation (and `local`)."""
    d = SCHEMATIC_REST[SMPL_JOINT_NAMES.index(b)] - SCHEMATIC_REST[SMPL_JOINT_NAMES.index(a)]
    if local is not None:
        d = local.apply(d)
    d = Rotation.from_rotvec([np.pi / 2, 0, 0]).apply(d)
    return d / np.linalg.norm(d)


def _smpl_leg() -> float:
    p = {n: SCHEMATIC_REST[i] for i, n in enumerate(SMPL_JOINT_NAMES)}
    return float(np.linalg.norm(p["left_knee"] - p["left_hip"]) + np.linalg.norm(p["left_ankle"] - p["left_knee"]))


def test_amass_onto_an_smpl_avatar_keeps_every_rotation(tmp_path):
    """Same skeleton: every body joint pairs by name and its local rotation is the file's, exactly."""
    rng = np.random.default_rng(0)
    poses = smplh_poses(3)
    poses[:, 3:66] = rng.normal(0, 0.4, (3, 63))
    path = amass_file(tmp_path / "amass.npz", poses, np.zeros((3, 3)))
    rest = SCHEMATIC_REST * 1.1 + np.array([0.0, 0.2, 0.0])  # an SMPL body of another size, elsewhere
    rig = Rig(list(SMPL_JOINT_NAMES), SMPL_PARENTS, rest)
    motion = read_motion_file(path, rig, 24)
    got = Rotation.from_rotvec(motion.poses[:, 1:22].reshape(-1, 3)).as_matrix()
    want = Rotation.from_rotvec(poses[:, 3:66].reshape(-1, 3)).as_matrix()
    assert np.allclose(got, want, atol=1e-6)
    assert np.allclose(motion.poses[:, 22:], 0)  # SMPL-H finger joints are not SMPL's hand joints: left at rest


def test_resampling_matches_the_closed_form(tmp_path):
    """A joint turning at 3 rad/s about z and a root moving at 2 m/s, filmed at 120 fps for 0.1 s, resampled to
    30 fps: 4 frames at t = 0, 1/30, 2/30, 3/30 with angle 3 t and position 2 t."""
    t = np.arange(13) / 120.0
    poses = np.zeros((13, 17, 3), np.float32)
    poses[:, 5, 2] = 3.0 * t
    roots = np.tile(np.eye(4, dtype=np.float32), (13, 1, 1))
    roots[:, 0, 3] = 2.0 * t
    roots[:, :3, :3] = Rotation.from_rotvec(np.outer(0.5 * t, [0, 0, 1])).as_matrix()
    out = resample(Motion(poses, roots, 120.0, "test"), 30.0)
    t_out = np.arange(4) / 30.0
    assert out.num_frames == 4 and out.fps == 30.0
    assert np.allclose(out.poses[:, 5, 2], 3.0 * t_out, atol=1e-6)
    assert np.allclose(out.poses[:, [0, 1, 2, 3, 4, 6]], 0, atol=1e-7)
    assert np.allclose(out.roots[:, 0, 3], 2.0 * t_out, atol=1e-6)
    assert np.allclose(Rotation.from_matrix(out.roots[:, :3, :3]).as_rotvec()[:, 2], 0.5 * t_out, atol=1e-6)
    up = resample(Motion(poses, roots, 120.0, "test"), 240.0)  # upsampling halves the step
    assert up.num_frames == 25 and np.allclose(up.poses[:, 5, 2], 3.0 * np.arange(25) / 240.0, atol=1e-6)
    same = resample(Motion(poses, roots, None, "test"), 30.0)  # unknown rate: left alone
    assert same.num_frames == 13 and same.fps == 30.0


def test_studio_params_folder_reads_back_and_a_wrong_body_is_refused(tmp_path):
    rng = np.random.default_rng(1)
    poses = rng.normal(0, 0.3, (3, 17, 3)).astype(np.float32)
    rh, th = rng.normal(0, 1, (3, 3)), rng.normal(0, 1, (3, 3))
    (tmp_path / "params").mkdir()
    for i in range(3):  # written as the studio writes them (framework.data.zju.layout)
        save_pickled_dict(
            tmp_path / "params" / f"{i}.npy",
            {
                "poses": poses[i].reshape(1, -1),
                "Rh": rh[i : i + 1],
                "Th": th[i : i + 1],
                "shapes": np.zeros((1, 10)),
                "body": "procedural",
            },
        )
    motion = read_motion_file(tmp_path, None, 17)
    assert np.allclose(motion.poses, poses)
    assert np.allclose(motion.roots[:, :3, :3], Rotation.from_rotvec(rh).as_matrix(), atol=1e-6)
    assert np.allclose(motion.roots[:, :3, 3], th, atol=1e-6)
    one = read_motion_file(tmp_path / "params" / "2.npy", None, 17)
    assert one.num_frames == 1 and np.allclose(one.poses[0], poses[2])
    np.savez(tmp_path / "poses.npz", poses=poses, fps=50.0)
    assert read_motion_file(tmp_path / "poses.npz", None, 17).fps == 50.0
    with pytest.raises(SplatrigError, match=r"expected \[F, 22, 3\]"):
        read_motion_file(tmp_path / "poses.npz", None, 22)


@pytest.fixture(scope="module")
def tiny(tiny_avatar):
    return tiny_avatar


def test_bvh_moves_the_left_arm_gaussians_of_a_trained_avatar_up(tiny, tmp_path, monkeypatch):
    from framework.animation.frames import posed_gaussians
    from framework.animation.sources import load_motion

    ckpt, cache = tiny
    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(cache))
    module, dm = load_tiny(ckpt)
    path = write_bvh(tmp_path / "raise.bvh", [{}, {"LeftArm": (80.0, 0.0, 0.0)}], 0.5)
    motion, frames = load_motion(module, dm, str(path))
    assert frames == [-1, -1]
    with pytest.raises(SplatrigError, match="missing.bvh"):
        load_motion(module, dm, str(tmp_path / "missing.bvh"))
    names = module.avatar.body.joint_names
    owner = (
        module.avatar.gaussians.params["skin_weights"].argmax(1)
        if "skin_weights" in module.avatar.gaussians.params
        else None
    )
    if owner is None:
        module.bake_weights()
        owner = module.avatar.gaussians.params["skin_weights"].argmax(1)
    left = torch.isin(owner, torch.tensor([names.index(n) for n in ("lowerarm.L", "hand.L")]))
    right = torch.isin(owner, torch.tensor([names.index(n) for n in ("lowerarm.R", "hand.R")]))
    assert left.sum() > 3 and right.sum() > 3
    z = [
        posed_gaussians(module, torch.as_tensor(motion.poses[i]), torch.as_tensor(motion.roots[i])).means[:, 2]
        for i in range(2)
    ]
    rise = float((z[1] - z[0])[left].mean())
    assert rise > 0.25  # forearm and hand rise by tens of centimetres
    # the right arm stays, up to the little weight the paper's additive residual w0 + F_dw may give any joint (the
    # tiny avatar's F_dw is random, ~0.05 per joint): the softmax form gave ~0 there
    assert float((z[1] - z[0])[right].abs().max()) < 0.1 * rise


def test_render_entry_point_plays_a_bvh_at_the_video_frame_rate(tiny, tmp_path):
    """8 BVH frames at 40 fps last 0.175 s: at fps=20 the video has frames at 0, 0.05, 0.1, 0.15 s."""
    ckpt, cache = tiny
    frames = [{"LeftArm": (10.0 * i, 0.0, 0.0)} for i in range(8)]
    path = write_bvh(tmp_path / "wave.bvh", frames, 0.025)
    env = dict(os.environ, SPLATRIG_CACHE_DIR=str(cache))
    out = tmp_path / "video"
    cmd = [
        sys.executable,
        "-m",
        "framework.render",
        f"ckpt={ckpt}",
        f"motion={path}",
        "cameras=fixed",
        "fps=20",
        "resolution=32",
        f"out_dir={out}",
    ]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "rendering" in proc.stderr  # the progress bar
    assert sorted(p.name for p in (out / "frames").iterdir()) == [f"{i:05d}.png" for i in range(4)]
    assert (out / "render_wave_fixed.mp4").stat().st_size > 0


def test_a_motion_file_drives_a_body_with_frozen_joints_through_its_full_skeleton(tmp_path):
    """`+scene=auto` may freeze joints; a BVH is then read onto the full skeleton (the poses the frozen body takes),
    giving the same poses as for the unfrozen body, which the frozen body folds on input."""
    from types import SimpleNamespace

    from framework.animation.sources import load_motion
    from framework.model.frozen_body import FrozenJointsBody
    from framework.plugins import load_plugins
    from framework.registry import BODIES

    load_plugins()
    base = BODIES.build("procedural")
    frozen = FrozenJointsBody(base, ["foot.L", "foot.R", "head"])
    path = write_bvh(tmp_path / "raise.bvh", [{}, {"LeftArm": (80.0, 0.0, 0.0)}], 0.5)
    dm = SimpleNamespace(train_set=SimpleNamespace(roots=lambda: None))  # a dataset without root transforms
    motion, frames = load_motion(SimpleNamespace(avatar=SimpleNamespace(body=frozen)), dm, str(path))
    want, _ = load_motion(SimpleNamespace(avatar=SimpleNamespace(body=base)), dm, str(path))
    assert motion.poses.shape == (2, base.num_joints, 3) and frames == [-1, -1]
    np.testing.assert_allclose(motion.poses, want.poses, atol=1e-6)
    assert frozen.input_pose(torch.as_tensor(motion.poses, dtype=torch.float32)).shape == (2, frozen.num_joints, 3)
