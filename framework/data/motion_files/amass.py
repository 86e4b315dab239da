"""AMASS-layout SMPL-family parameter files (.npz): `poses`, `trans`, `betas`, `mocap_framerate`.

What is read: `poses` [F, 3 * J] axis-angle with J = 24 (SMPL, 72 values), 52 (SMPL-H, 156: AMASS's usual) or 55
(SMPL-X, 165), of which the first 22 body joints are used (hands and face are dropped); or the SMPL-X split form
`root_orient` [F, 3] + `pose_body` [F, 63]. `trans` [F, 3] metres; `mocap_framerate` (SMPL-H files) or
`mocap_frame_rate` (SMPL-X files) in frames per second. `betas` and `gender` are ignored (the avatar keeps its own
body shape). AMASS's world is Z up; the global orientation (joint 0) turns SMPL's Y-up canonical body into it.

Joint mapping onto the avatar (see `framework.data.motion_files.retarget` for the method):

    SMPL joint            semantic joint   Anny (reduced)      procedural body
    pelvis                pelvis           root                pelvis
    left_hip / right_hip  hip.L / hip.R    upperleg01.L/.R     upperleg.L/.R
    left_knee             knee.L           lowerleg01.L/.R     lowerleg.L/.R
    left_ankle            ankle.L          foot.L/.R           foot.L/.R
    spine1                spine            spine04             spine
    spine3                chest            spine02             chest
    neck, head            neck, head       neck01, head        neck, head
    left_collar           clavicle.L       clavicle.L/.R       (none: folds into chest)
    left_shoulder         shoulder.L       upperarm01.L/.R     upperarm.L/.R
    left_elbow            elbow.L          lowerarm01.L/.R     lowerarm.L/.R
    left_wrist            wrist.L          wrist.L/.R          hand.L/.R
    spine2, left_foot,    (unpaired: their rotation reaches the avatar through the paired joints below them)
    right_foot

(right side likewise). An SMPL or SMPL-X avatar pairs every joint by name and takes the rotations as they are.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from framework.data.motion_files.retarget import SourceMotion
from framework.data.motion_files.smpl_skeleton import BODY_JOINTS, SCHEMATIC_REST, SMPL_JOINT_NAMES, SMPL_PARENTS
from framework.data.motions import SEMANTIC
from framework.errors import SplatrigError

FPS_KEYS = ("mocap_framerate", "mocap_frame_rate")


def is_amass_file(keys: list[str]) -> bool:
    """An AMASS-layout npz has `trans` and body poses (`poses`, or SMPL-X's `root_orient` + `pose_body`)."""
    return "trans" in keys and ("poses" in keys or {"root_orient", "pose_body"} <= set(keys))


def smpl_semantic() -> dict[str, str]:
    """SMPL joint name -> semantic joint, read off framework.data.motions.SEMANTIC (which lists SMPL's names)."""
    return {name: sem for sem, names in SEMANTIC.items() for name in names if name in SMPL_JOINT_NAMES}


def read_amass(path: str | Path, rest_positions: np.ndarray | None = None) -> SourceMotion:
    """The first 22 SMPL joints of an AMASS file; `rest_positions` [22, 3] replace the schematic T-pose (used when
    the avatar's body is SMPL itself, so that its own rest skeleton drives the rest-pose correction)."""
    path = Path(path)
    with np.load(path, allow_pickle=False) as data:
        keys = list(data.files)
        if not is_amass_file(keys):
            raise SplatrigError(
                f"motion file {path}: not in the AMASS layout; expected `poses` [F, 3J] and `trans` "
                f"[F, 3] (found keys {keys})."
            )
        if "poses" in keys:
            poses = np.asarray(data["poses"], dtype=np.float64)
        else:
            poses = np.concatenate([data["root_orient"], data["pose_body"]], axis=-1).astype(np.float64)
        trans = np.asarray(data["trans"], dtype=np.float64)
        fps = next((float(data[k]) for k in FPS_KEYS if k in keys), None)
    if poses.ndim != 2 or poses.shape[1] < 3 * BODY_JOINTS or trans.shape != (poses.shape[0], 3):
        raise SplatrigError(
            f"motion file {path}: `poses` has shape {poses.shape} and `trans` {trans.shape}; expected "
            f"[F, >= {3 * BODY_JOINTS}] and [F, 3]."
        )
    F = poses.shape[0]
    local = Rotation.from_rotvec(poses[:, : 3 * BODY_JOINTS].reshape(-1, 3)).as_matrix().reshape(F, BODY_JOINTS, 3, 3)
    glob = np.empty_like(local)
    for k in range(BODY_JOINTS):  # SMPL lists every parent before its children
        p = SMPL_PARENTS[k]
        glob[:, k] = local[:, k] if p < 0 else glob[:, p] @ local[:, k]
    rest = SCHEMATIC_REST[:BODY_JOINTS] if rest_positions is None else np.asarray(rest_positions, np.float64)
    return SourceMotion(
        joint_names=SMPL_JOINT_NAMES[:BODY_JOINTS],
        parents=SMPL_PARENTS[:BODY_JOINTS],
        rest_positions=rest,
        global_rotations=glob,
        root_positions=trans,
        semantic=smpl_semantic(),
        world_up=np.array([0.0, 0.0, 1.0]),
        fps=fps,
        source=str(path),
    )
