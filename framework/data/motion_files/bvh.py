"""BVH motion capture files, read with `bvhio` (PyPI), retargeted onto the avatar.

A BVH file defines a skeleton by OFFSETs (the rest pose, in the file's world and units) and, per frame, each joint's
rotation relative to that rest pose as Euler angles in the order its CHANNELS list (intrinsic, e.g. `Zrotation
Xrotation Yrotation` = Rz Rx Ry); the root also carries a position. bvhio parses the file and turns the angles into
quaternions; world rotations follow by composing them down the tree. Only the root's position channels are used
(other joints' translations, rare, are ignored). The frame rate is 1 / `Frame Time`.

Joints are recognised by name, case-insensitively and after dropping a namespace prefix (`mixamorig:LeftArm`):

    semantic     names (first found wins; right side: Right... / r...)
    pelvis       Hips, Pelvis, Root
    spine        Spine, Abdomen, LowerBack
    chest        Spine2, Chest, Spine1
    neck         Neck, Neck1
    head         Head
    clavicle.L   LeftShoulder, LeftCollar, lCollar
    shoulder.L   LeftArm, LeftUpArm, LeftUpperArm, lShldr
    elbow.L      LeftForeArm, LeftLowArm, LeftLowerArm, lForeArm
    wrist.L      LeftHand, LeftWrist, lHand
    hip.L        LeftUpLeg, LeftHip, LeftUpperLeg, lThigh
    knee.L       LeftLeg, LeftLowLeg, LeftLowerLeg, LeftKnee, lShin
    ankle.L      LeftFoot, LeftAnkle, lFoot

which covers the CMU, Mixamo and Biovision/Poser conventions; see `framework.data.motion_files.retarget` for how the
paired joints drive the avatar.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from framework.data.motion_files.retarget import SourceMotion
from framework.errors import SplatrigError

MIDDLE_NAMES = {
    "pelvis": ("hips", "pelvis", "root"),
    "spine": ("spine", "abdomen", "lowerback"),
    "chest": ("spine2", "chest", "spine1"),
    "neck": ("neck", "neck1"),
    "head": ("head",),
}
SIDE_NAMES = {  # {side} is left / right, {s} is l / r
    "clavicle": ("{side}shoulder", "{side}collar", "{s}collar"),
    "shoulder": ("{side}arm", "{side}uparm", "{side}upperarm", "{s}shldr"),
    "elbow": ("{side}forearm", "{side}lowarm", "{side}lowerarm", "{s}forearm"),
    "wrist": ("{side}hand", "{side}wrist", "{s}hand"),
    "hip": ("{side}upleg", "{side}hip", "{side}upperleg", "{s}thigh"),
    "knee": ("{side}leg", "{side}lowleg", "{side}lowerleg", "{side}knee", "{s}shin"),
    "ankle": ("{side}foot", "{side}ankle", "{s}foot"),
}


def name_table() -> dict[str, tuple[str, ...]]:
    """semantic joint -> candidate BVH names (normalised: lower case, no namespace), first found wins."""
    table = dict(MIDDLE_NAMES)
    for part, patterns in SIDE_NAMES.items():
        for tag, side, s in (("L", "left", "l"), ("R", "right", "r")):
            table[f"{part}.{tag}"] = tuple(p.format(side=side, s=s) for p in patterns)
    return table


def normalise_name(name: str) -> str:
    return name.rsplit(":", 1)[-1].replace("_", "").replace(" ", "").lower()


def bvh_semantic(joint_names: list[str]) -> dict[str, str]:
    """joint name -> semantic joint for the joints of this skeleton the name table recognises."""
    by_norm = {normalise_name(n): n for n in joint_names}
    out: dict[str, str] = {}
    for sem, candidates in name_table().items():
        for cand in candidates:
            name = by_norm.get(cand)
            if name is not None and name not in out:
                out[name] = sem
                break
    return out


def read_bvh(path: str | Path) -> SourceMotion:
    """Skeleton, per-frame world rotations and root positions of a BVH file."""
    import warnings

    with warnings.catch_warnings():  # bvhio imports PyGLM by a name PyGLM plans to retire; nothing to act on here
        warnings.simplefilter("ignore", PendingDeprecationWarning)
        import bvhio

    path = Path(path)
    try:
        container = bvhio.readAsBvh(str(path))
    except (SyntaxError, ValueError, IndexError) as exc:
        raise SplatrigError(
            f"motion file {path}: not a readable BVH file ({exc}); expected HIERARCHY ... MOTION."
        ) from exc
    layout = container.Root.layout()  # [(joint, index, depth)] depth-first
    joints = [j for j, _, _ in layout]
    parents, stack = [], []  # stack[d] = index of the last joint seen at depth d
    for i, (_, _, depth) in enumerate(layout):
        del stack[depth:]
        parents.append(stack[-1] if stack else -1)
        stack.append(i)
    F, S = int(container.FrameCount), len(joints)
    if F < 1 or any(len(j.Keyframes) != F for j in joints):
        raise SplatrigError(
            f"motion file {path}: {F} frames declared but the MOTION section holds a different "
            f"number of rows; expected one row of channel values per frame."
        )
    offsets = np.array([[j.Offset.x, j.Offset.y, j.Offset.z] for j in joints], dtype=np.float64)  # [S, 3]
    rest = np.zeros((S, 3))
    for k in range(S):
        rest[k] = offsets[k] + (rest[parents[k]] if parents[k] >= 0 else 0.0)
    quats = np.array([[[q.x, q.y, q.z, q.w] for q in (key.Rotation for key in j.Keyframes)] for j in joints])
    local = Rotation.from_quat(quats.reshape(-1, 4)).as_matrix().reshape(S, F, 3, 3).swapaxes(0, 1)  # [F, S, 3, 3]
    glob = np.empty_like(local)
    for k in range(S):  # depth-first order: parents come first
        glob[:, k] = local[:, k] if parents[k] < 0 else glob[:, parents[k]] @ local[:, k]
    root = joints[0]
    root_positions = np.array([[key.Position.x, key.Position.y, key.Position.z] for key in root.Keyframes])
    names = [j.Name for j in joints]
    frame_time = float(container.FrameTime)
    return SourceMotion(
        joint_names=names,
        parents=np.asarray(parents),
        rest_positions=rest,
        global_rotations=glob,
        root_positions=root_positions,
        semantic=bvh_semantic(names),
        world_up=None,
        fps=1.0 / frame_time if frame_time > 0 else None,
        source=str(path),
    )
