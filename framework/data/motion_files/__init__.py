"""Motion files that drive a trained avatar: our pose files, AMASS-layout SMPL-family files and BVH, retargeted onto
the avatar's body and resampled to a frame rate.

May import framework core (types, errors), framework.rig (kinematics), framework.bodies (SMPL joint names),
framework.data (Rig, the ZJU layout) and numpy / scipy / bvhio; never lightning/, model/ or the entry points.
"""

from __future__ import annotations

import pickle
import zipfile
from pathlib import Path

import numpy as np

from framework.data.motion_files.clip import Motion, resample
from framework.data.motions import Rig
from framework.errors import SplatrigError

__all__ = ["Motion", "read_motion_file", "resample"]


def read_motion_file(
    path: str | Path, rig: Rig | None, num_joints: int, reference_root: np.ndarray | None = None
) -> Motion:
    """Any supported motion file (or params folder) as poses of the avatar's body (`num_joints` joints).

    Pose files (framework.data.motion_files.studio) must already be for this body; AMASS (.npz with `trans`) and BVH
    files are retargeted onto `rig` (framework.data.motion_files.retarget), placed relative to `reference_root`
    [4, 4] (the avatar's first training frame's root transform) when given. A file numpy cannot read, or a frame
    with a non-finite value, is a SplatrigError naming the file (and the frame).
    """
    try:
        motion = _read_motion(Path(path), rig, num_joints, reference_root)
    except (OSError, EOFError, zipfile.BadZipFile, pickle.UnpicklingError) as exc:
        raise SplatrigError(
            f"motion={path}: cannot be read ({type(exc).__name__}: the file is truncated or not in "
            f"the format its suffix says); re-export it."
        ) from None
    for name, values in (("poses", motion.poses), ("roots", motion.roots)):
        if values is not None and not np.isfinite(values).all():
            frame = int(np.flatnonzero((~np.isfinite(values.reshape(values.shape[0], -1))).any(1))[0])
            raise SplatrigError(
                f"motion={path}: `{name}` of frame {frame} holds a non-finite value; expected "
                f"finite numbers (re-export the motion or drop that frame)."
            )
    return motion


def _read_motion(path: Path, rig: Rig | None, num_joints: int, reference_root: np.ndarray | None) -> Motion:
    from framework.data.motion_files.amass import is_amass_file, read_amass
    from framework.data.motion_files.bvh import read_bvh
    from framework.data.motion_files.retarget import retarget
    from framework.data.motion_files.smpl_skeleton import BODY_JOINTS, SMPL_JOINT_NAMES
    from framework.data.motion_files.studio import read_pose_file

    if not path.exists():
        raise SplatrigError(
            f"motion={path}: no such file or folder; expected a pose file (.npz/.npy), a params "
            f"folder, an AMASS-layout .npz or a .bvh file."
        )

    def needs_rig() -> Rig:
        if rig is None:
            raise SplatrigError(
                f"motion={path}: retargeting needs the body's joints named (pelvis, hips, knees, "
                f"shoulders; framework.data.motions.SEMANTIC), and this body's are not."
            )
        return rig

    if path.suffix.lower() == ".bvh":
        return retarget(read_bvh(path), needs_rig(), reference_root)
    if path.suffix == ".npz":
        with np.load(path, allow_pickle=False) as data:
            keys = list(data.files)
        if is_amass_file(keys):
            target = needs_rig()
            smpl_names = SMPL_JOINT_NAMES[:BODY_JOINTS]
            own = None
            if all(n in target.joint_names for n in smpl_names):  # an SMPL-family avatar: its own rest skeleton
                own = target.rest_joints[[target.joint_names.index(n) for n in smpl_names]]
            return retarget(read_amass(path, own), target, reference_root)
        if "poses" not in keys:
            raise SplatrigError(
                f"motion={path}: an .npz without `poses`; expected our pose file (`poses` "
                f"[F, J, 3]) or the AMASS layout (`poses`, `trans`, `mocap_framerate`); found "
                f"{keys}."
            )
    if path.is_dir() or path.suffix in (".npz", ".npy"):
        return read_pose_file(path, num_joints)
    raise SplatrigError(
        f"motion={path}: unknown motion file type '{path.suffix}'; expected .npz, .npy, .bvh or a params folder."
    )
