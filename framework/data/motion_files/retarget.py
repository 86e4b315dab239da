"""Retargeting: a motion recorded on another skeleton (AMASS SMPL-family files, BVH) onto the avatar's body.

The method is rotation transfer with a rest-pose correction, as mocap retargeting tools do it:
1. Pair joints. A source joint pairs with the target joint of the same name when the target has one (AMASS onto an
   SMPL avatar), otherwise through the semantic joints of `framework.data.motions.SEMANTIC` (pelvis, spine, chest,
   neck, head, clavicle/shoulder/elbow/wrist, hip/knee/ankle on each side). Target joints without a partner keep
   their parent's world rotation (no local rotation); source joints without one (fingers, toes, extra spine
   segments) only act through their paired descendants.
2. Body frames. Each skeleton's canonical axes come from its own rest joints: left = left hip - right hip, up = mid
   shoulders - pelvis (made orthogonal to left), forward = left x up. C = B_t B_s^T maps source canonical
   directions to target ones, so a Y-up SMPL or BVH skeleton drives a Z-up Anny body and vice versa.
3. Rest-pose correction. For a paired joint whose bone (joint -> its semantic child, e.g. shoulder -> elbow) exists
   in both skeletons, Q_k is the smallest rotation turning the target's rest bone onto the source's (a T-pose
   source driving an A-pose target lifts the arms by Q at rest); joints without a bone inherit their ancestor's Q.
4. World rotations. With G_s the source joint's world rotation relative to its rest pose, the target's is
   G_t = W G_s C^T Q_k, so every paired bone points where the source's bone points (rotated by W). Local target
   rotations follow as G_t(parent)^T G_t(k), the body's pose convention.
5. Placement. W turns the source's world (its up axis; its heading at frame 0) into the avatar's reference frame:
   the root transform of the first training frame, so the motion starts where and facing how the avatar stood in its
   training data (identity when there is none). The root's heading about the world up goes into the root transform
   (like EasyMocap's Rh), the remaining tilt into the root joint's rotation; the pelvis moves by the source root's
   displacement scaled by the ratio of leg lengths (target / source), so units (cm, inches, m) do not matter.
Shape (SMPL betas, BVH bone lengths) is not transferred: the avatar keeps its own body.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from framework.data.motion_files.clip import Motion
from framework.data.motions import CHILD, Rig
from framework.errors import SplatrigError
from framework.rig.kinematics import kinematic_levels

REQUIRED = ("pelvis", "hip.L", "hip.R", "shoulder.L", "shoulder.R")


class RetargetError(SplatrigError, ValueError):
    """A motion's skeleton lacks joints retargeting needs; the message names the file and the missing joints."""


@dataclass
class SourceMotion:
    """A motion on its own skeleton, as read from a file, before retargeting."""

    joint_names: list[str]
    parents: np.ndarray  # [S] int, -1 at the root
    rest_positions: np.ndarray  # [S, 3] rest joint positions in the source's canonical frame (its own units)
    global_rotations: np.ndarray  # [F, S, 3, 3] world rotation of each joint relative to its rest pose
    root_positions: np.ndarray  # [F, 3] world position of the root joint (source units)
    semantic: dict[str, str]  # source joint name -> semantic joint (keys of framework.data.motions.SEMANTIC)
    world_up: np.ndarray | None  # [3] up in the source's world; None: the rest skeleton's up (BVH: world = rest)
    fps: float | None
    source: str

    @property
    def num_frames(self) -> int:
        return int(self.global_rotations.shape[0])


def _unit(v: np.ndarray) -> np.ndarray:
    return v / max(float(np.linalg.norm(v)), 1e-12)


def body_frame(positions: np.ndarray, index: dict[str, int]) -> np.ndarray:
    """[3, 3] with columns (left, up, forward) of a skeleton at rest, from its hips, shoulders and pelvis."""
    left = _unit(positions[index["hip.L"]] - positions[index["hip.R"]])
    up = 0.5 * (positions[index["shoulder.L"]] + positions[index["shoulder.R"]]) - positions[index["pelvis"]]
    up = _unit(up - (up @ left) * left)
    return np.stack([left, up, np.cross(left, up)], axis=1)


def smallest_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """[3, 3] rotation turning unit vector a onto b by the smallest angle (pi about a normal when opposite)."""
    a, b = _unit(a), _unit(b)
    axis = np.cross(a, b)
    s, c = float(np.linalg.norm(axis)), float(np.clip(a @ b, -1.0, 1.0))
    if s < 1e-9:
        if c > 0:
            return np.eye(3)
        normal = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        return Rotation.from_rotvec(_unit(normal) * np.pi).as_matrix()
    return Rotation.from_rotvec(axis / s * np.arctan2(s, c)).as_matrix()


def _leg_length(positions: np.ndarray, index: dict[str, int]) -> float:
    hip, knee = positions[index["hip.L"]], positions[index.get("knee.L", index["hip.L"])]
    ankle = positions[index["ankle.L"]] if "ankle.L" in index else knee + (knee - hip)
    return float(np.linalg.norm(knee - hip) + np.linalg.norm(ankle - knee))


def joint_pairs(src: SourceMotion, rig: Rig) -> dict[int, int]:
    """target joint index -> source joint index (same name first, else the same semantic joint)."""
    pairs: dict[int, int] = {}
    for s, name in enumerate(src.joint_names):
        if name in rig.joint_names:
            pairs[rig.joint_names.index(name)] = s
        elif src.semantic.get(name) in rig.index:
            pairs.setdefault(rig.index[src.semantic[name]], s)
    return pairs


def retarget(src: SourceMotion, rig: Rig, reference_root: np.ndarray | None = None) -> Motion:
    """The source motion on `rig`'s body: poses [F, J, 3] and root transforms [F, 4, 4] (module docstring)."""
    src_index = {sem: src.joint_names.index(n) for n, sem in src.semantic.items() if n in src.joint_names}
    missing = [sem for sem in REQUIRED if sem not in src_index or sem not in rig.index]
    if missing:
        raise RetargetError(
            f"motion file {src.source}: no joints for {missing} were found (source joints: "
            f"{', '.join(src.joint_names[:24])}); retargeting needs a pelvis, both hips and both shoulders. Rename "
            f"them in the file or add their names to the tables in framework/data/motion_files/."
        )
    pairs = joint_pairs(src, rig)
    P_s, P_t = np.asarray(src.rest_positions, np.float64), np.asarray(rig.rest_joints, np.float64)
    B_s, B_t = body_frame(P_s, src_index), body_frame(P_t, rig.index)
    C = B_t @ B_s.T  # source canonical -> target canonical

    J, parents = rig.num_joints, [int(p) for p in rig.parents]
    order = [k for ids, _ in kinematic_levels(parents) for k in ids]  # parents before children
    target_sem = {t: sem for sem, t in rig.index.items()}
    Q = np.tile(np.eye(3), (J, 1, 1))
    for k in order:
        child = CHILD.get(target_sem.get(k, ""))
        if k in pairs and child in rig.index and child in src_index:
            d_t = P_t[rig.index[child]] - P_t[k]
            d_s = C @ (P_s[src_index[child]] - P_s[pairs[k]])
            Q[k] = smallest_rotation(d_t, d_s)
        elif parents[k] >= 0:
            Q[k] = Q[parents[k]]

    # W: source world -> avatar world, matching up axes and the heading of frame 0 to the reference's
    G_s = np.asarray(src.global_rotations, np.float64)  # [F, S, 3, 3]
    R_ref = np.eye(3) if reference_root is None else np.asarray(reference_root, np.float64)[:3, :3]
    t_ref = np.zeros(3) if reference_root is None else np.asarray(reference_root, np.float64)[:3, 3]
    u_s = _unit(np.asarray(src.world_up, np.float64)) if src.world_up is not None else B_s[:, 1]
    u_t = R_ref @ B_t[:, 1]

    def horizontal(v: np.ndarray, up: np.ndarray) -> np.ndarray:
        """v without its component along `up`; any horizontal direction when v is vertical (lying on the back)."""
        h = v - (v @ up) * up
        if np.linalg.norm(h) < 1e-6:
            h = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
        return _unit(h)

    h_s = horizontal(G_s[0, src_index["pelvis"]] @ B_s[:, 2], u_s)
    h_t = horizontal(R_ref @ B_t[:, 2], u_t)
    W = np.stack([h_t, u_t, np.cross(h_t, u_t)], 1) @ np.stack([h_s, u_s, np.cross(h_s, u_s)], 1).T

    F = src.num_frames
    G_t = np.empty((F, J, 3, 3))
    for k in order:
        if k in pairs:
            G_t[:, k] = W @ G_s[:, pairs[k]] @ C.T @ Q[k]
        elif parents[k] >= 0:
            G_t[:, k] = G_t[:, parents[k]]
        else:
            raise RetargetError(
                f"motion file {src.source}: the avatar's root joint '{rig.joint_names[k]}' has no "
                f"partner in the motion's skeleton."
            )
    local = G_t.copy()
    for k in order:
        if parents[k] >= 0:
            local[:, k] = np.swapaxes(G_t[:, parents[k]], -1, -2) @ G_t[:, k]

    # root: heading about the world up -> root transform, the rest -> the root joint's rotation
    root = order[0]
    fwd = G_t[:, root] @ B_t[:, 2]  # [F, 3]
    fwd = fwd - (fwd @ u_t)[:, None] * u_t
    yaw = np.arctan2(np.cross(h_t, fwd) @ u_t, fwd @ h_t)  # [F]
    R_root = Rotation.from_rotvec(yaw[:, None] * u_t).as_matrix() @ R_ref  # [F, 3, 3]
    local[:, root] = np.swapaxes(R_root, -1, -2) @ G_t[:, root]
    scale = _leg_length(P_t, rig.index) / max(_leg_length(P_s, src_index), 1e-9)
    j0 = P_t[root]
    pelvis = R_ref @ j0 + t_ref + scale * (np.asarray(src.root_positions, np.float64) - src.root_positions[0]) @ W.T
    roots = np.tile(np.eye(4), (F, 1, 1))
    roots[:, :3, :3] = R_root
    roots[:, :3, 3] = pelvis - R_root @ j0
    poses = Rotation.from_matrix(local.reshape(-1, 3, 3)).as_rotvec().reshape(F, J, 3)
    return Motion(poses.astype(np.float32), roots.astype(np.float32), src.fps, src.source)
