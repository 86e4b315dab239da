"""Where an avatar's poses come from: a split of its training data (`train`, `novel_pose`, ...) or a motion file."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from framework.data.motion_files import Motion, read_motion_file, resample
from framework.data.motions import Rig
from framework.errors import SplatrigError

SPLITS = ("train", "novel_view", "novel_pose")


def reference_root(dm) -> np.ndarray | None:
    """[4, 4] root transform of the first training frame (where retargeted motions start), None without roots."""
    train = dm.train_set
    roots = train.roots()
    if roots is None:
        return None
    return roots[train.frame_ids[0]].double().numpy()


def body_rig(body) -> Rig | None:
    """The body's skeleton with its semantic joints, or None when they cannot be named (then no retargeting)."""
    try:
        return Rig.from_body(body)
    except ValueError:
        return None


def load_motion(module, dm, spec: str, fps: float | None = None) -> tuple[Motion, list[int]]:
    """(motion, frame ids) for a split name or a motion file; frame ids index the training sequence for splits (pose
    refinement looks them up) and are -1 for files. With `fps`, a file's motion is resampled to that frame rate."""
    body = module.avatar.body
    if body is None:
        raise SplatrigError(
            f"motion={spec}: this model has no body (a static scene); render it with a split of views "
            f"instead of a motion."
        )
    path = Path(spec)
    if spec in SPLITS and not path.exists():
        dataset = dm.split(spec)
        frames = list(dataset.frame_ids)
        poses = dataset.poses()[frames].numpy()
        roots = dataset.roots()
        roots = None if roots is None else roots[frames].numpy()
        return Motion(poses, roots, None, spec), frames
    if not path.exists() and not path.suffix:
        raise SplatrigError(f"motion={spec}: neither a split ({', '.join(SPLITS)}) nor an existing motion file.")
    # a body with frozen joints takes poses of its full skeleton (body.input_pose folds them), so retarget onto that
    skeleton = body.input_body
    motion = read_motion_file(path, body_rig(skeleton), skeleton.num_joints, reference_root(dm))
    if fps:
        motion = resample(motion, float(fps))
    return motion, [-1] * motion.num_frames
