"""Our own pose files: the studio's / ZJU-MoCap's per-frame params and the plain `.npz` / `.npy` pose arrays.

Accepted (the poses must be for the avatar's own body: same joints, no retargeting):
- `poses.npz` with `poses` [F, J, 3] axis-angle, optional `roots` [F, 4, 4] (world = root @ body) and `fps`;
- `poses.npy` holding [F, J, 3];
- a ZJU-MoCap-layout params folder (`params/` or `new_params/` of a sequence, or the sequence folder itself), whose
  `{i}.npy` files hold dicts with `poses` [1, 3J], `Rh` [1, 3], `Th` [1, 3] (framework.data.zju.layout), read in
  frame-number order; or a single such file (one frame). Root transform = [[R(Rh), Th], [0, 1]].
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from framework.data.motion_files.clip import Motion
from framework.data.zju.layout import PARAMS_DIRS, ZjuFormatError, load_pickled_dict
from framework.errors import SplatrigError


def _params_files(path: Path) -> list[Path]:
    for sub in PARAMS_DIRS:
        if (path / sub).is_dir():
            path = path / sub
            break
    files = [p for p in path.glob("*.npy") if p.stem.isdigit()]
    if not files:
        raise SplatrigError(
            f"motion={path}: no params files ({{i}}.npy) found; expected a ZJU-MoCap params folder "
            f"or a sequence folder holding params/."
        )
    return sorted(files, key=lambda p: int(p.stem))


def _from_params(files: list[Path], source: str) -> Motion:
    from scipy.spatial.transform import Rotation

    poses, roots = [], []
    for f in files:
        d = load_pickled_dict(f)
        if not {"poses", "Rh", "Th"} <= set(d):
            raise ZjuFormatError(f"{f}: expected keys poses, Rh, Th, found {sorted(d)}")
        poses.append(np.asarray(d["poses"], np.float32).reshape(-1, 3))
        root = np.eye(4)
        root[:3, :3] = Rotation.from_rotvec(np.asarray(d["Rh"], np.float64).reshape(3)).as_matrix()
        root[:3, 3] = np.asarray(d["Th"], np.float64).reshape(3)
        roots.append(root)
    sizes = {p.shape[0] for p in poses}
    if len(sizes) != 1:
        raise ZjuFormatError(f"{source}: params files hold different joint counts {sorted(sizes)}.")
    return Motion(np.stack(poses), np.stack(roots).astype(np.float32), None, source)


def is_pose_array_file(path: Path, keys: list[str] | None) -> bool:
    """Our `.npy` arrays / `.npz` with `poses` [F, J, 3] (as opposed to AMASS's 2-D poses with `trans`)."""
    return path.suffix == ".npy" or (keys is not None and "poses" in keys and "trans" not in keys)


def read_pose_file(path: str | Path, num_joints: int) -> Motion:
    """A studio pose file or params folder as a Motion; its poses must have `num_joints` joints."""
    path = Path(path)
    source = str(path)
    if path.is_dir():
        motion = _from_params(_params_files(path), source)
    elif path.suffix == ".npy":
        data = np.load(path, allow_pickle=True)
        if data.dtype == object:  # a single params file: np.save of a dict
            motion = _from_params([path], source)
        else:
            motion = Motion(np.asarray(data, np.float32), None, None, source)
    else:
        with np.load(path, allow_pickle=False) as data:
            poses = np.asarray(data["poses"], np.float32)
            roots = np.asarray(data["roots"], np.float32) if "roots" in data.files else None
            fps = float(data["fps"]) if "fps" in data.files else None
        motion = Motion(poses, roots, fps, source)
    if motion.poses.ndim != 3 or motion.poses.shape[1:] != (num_joints, 3):
        raise SplatrigError(
            f"motion={path}: poses have shape {tuple(motion.poses.shape)}, expected [F, {num_joints}, 3] for the "
            f"avatar's body. Pose files must be made for this body; use an AMASS .npz or a .bvh file to retarget "
            f"a motion from another skeleton."
        )
    if motion.roots is not None and motion.roots.shape != (motion.num_frames, 4, 4):
        raise SplatrigError(
            f"motion={path}: roots have shape {tuple(motion.roots.shape)}, expected [{motion.num_frames}, 4, 4]."
        )
    return motion
