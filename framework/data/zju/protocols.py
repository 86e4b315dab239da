"""Published view/frame splits of ZJU-MoCap and H36M sequences (`protocol=` of the `zju_mocap` dataset).

- "aninerf_4view": Animatable NeRF (zju3dv/animatable_nerf, configs/aninerf_{313,315,377,386}.yaml and
  configs/aligned_nerf_pdf/aligned_aninerf_pdf_{387,390,392,393,394}.yaml;
  H36M: configs/aninerf_s{1,5,6,7,8,9,11}p.yaml):
  ZJU training views [0, 6, 12, 18], test views = every other view; H36M training views [0, 1, 2], test view [3].
  Training frames begin_ith_frame + k * frame_interval for k < num_train_frame; novel-pose frames follow the training
  frames (num_eval_frame of them; CoreView_390 evaluates novel poses from frame 0). Evaluation takes every 30th frame of
  the split's frame list (their test FrameSampler, `cfg.test.frame_sampler_interval = 30`).
- "dense": every view except the held-out views {v : v % 6 == 3} (3, 9, 15, 21 on a 23-camera rig) for training; those
  held-out views for testing; frames as in "aninerf_4view". There is no single published dense-view protocol for
  these data; this one is ours and keeps a held-out view in each quarter of the ring.
- None: everything from the explicit arguments (train_views / test_views / train_frames / novel_pose_frames).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

# sequence -> (begin_ith_frame, num_train_frame, frame_interval, num_eval_frame, novel_pose_begin or None)
PROTOCOL_FRAMES: dict[str, tuple[int, int, int, int, int | None]] = {
    "313": (0, 60, 1, 1000, None),
    "315": (0, 400, 1, 1000, None),
    "377": (0, 300, 1, 200, None),
    "386": (0, 300, 1, 346, None),
    "387": (0, 300, 1, 1000, None),
    "390": (700, 300, 1, 700, 0),
    "392": (0, 300, 1, 1000, None),
    "393": (0, 300, 1, 1000, None),
    "394": (0, 300, 1, 1000, None),
    "S1": (0, 150, 5, 49, None),
    "S5": (0, 250, 5, 127, None),
    "S6": (0, 150, 5, 83, None),
    "S7": (0, 300, 5, 200, None),
    "S8": (0, 250, 5, 87, None),
    "S9": (0, 260, 5, 133, None),
    "S11": (0, 200, 5, 82, None),
}
PROTOCOLS = ("aninerf_4view", "dense")
EVAL_FRAME_STEP = 30


def sequence_key(root: Path) -> str | None:
    """ "313" for .../CoreView_313, "S9" for .../S9/Posing; None when the path names no known sequence."""
    for part in reversed(root.resolve().parts):
        m = re.fullmatch(r"(?:CoreView_|my_)?(\d{3})", part)
        if m and m.group(1) in PROTOCOL_FRAMES:
            return m.group(1)
        if part in PROTOCOL_FRAMES:
            return part
    return None


@dataclass(frozen=True)
class ProtocolPreset:
    """What a protocol fixes for one sequence; explicit dataset arguments override each field."""

    train_views: list[int]
    train_frames: Any = None  # (start, end, step) or None
    novel_pose_frames: Any = None
    eval_frame_step: int = 1


def protocol_preset(protocol: str | None, sequence: str | None, num_views: int) -> ProtocolPreset:
    """The preset of `protocol` for `sequence` on a rig of `num_views` cameras (frames None: the sequence is not in
    the published table, so the caller must give them)."""
    views_all = list(range(num_views))
    if protocol is None:
        return ProtocolPreset(train_views=views_all)
    if protocol not in PROTOCOLS:
        raise ValueError(f"zju_mocap: unknown protocol '{protocol}'; known: {', '.join(PROTOCOLS)} or null")
    h36m = sequence is not None and sequence.startswith("S")
    if protocol == "aninerf_4view":
        views = [0, 1, 2] if h36m else [0, 6, 12, 18]
    else:
        views = [v for v in views_all if v % 6 != 3]
    views = [v for v in views if v < num_views]
    if sequence not in PROTOCOL_FRAMES:
        return ProtocolPreset(train_views=views)
    b, n, step, ne, pose_begin = PROTOCOL_FRAMES[sequence]
    pb = b + n * step if pose_begin is None else pose_begin
    return ProtocolPreset(views, (b, b + n * step, step), (pb, pb + ne * step, step), EVAL_FRAME_STEP)
