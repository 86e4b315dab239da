"""Dataset `zju_mocap`: ZJU-MoCap, H36M and CMU Panoptic sequences in the Neural Body / Animatable NeRF layout
(and the synthetic studio, written in the same layout). The layout itself is documented in
`framework.data.zju_format`.

Samples, images, masks, boundary masks, cameras, body parameters and bounds follow the conventions shared with every
sequence reader (`framework.data.sequence_dataset`): stored K/D/R/T with T in millimetres, undistortion keeping K,
area downscaling, root = [[R(Rh), Th], [0, 1]].

Protocols (`protocol=`): presets that make results comparable with published tables.
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
Explicit arguments always override the preset's values.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

from framework.data.sequence_dataset import SequenceDataset
from framework.data.zju_format import ZjuSequence, check_body_compatible
from framework.registry import register

__all__ = ["ZjuMocapDataset", "check_body_compatible", "PROTOCOL_FRAMES"]

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


@register("dataset", "zju_mocap")
class ZjuMocapDataset(SequenceDataset):
    """One split of a ZJU-MoCap-layout sequence; see the module docstring for conventions and protocols."""

    def __init__(
        self,
        root: str,
        split: str = "train",
        protocol: str | None = "aninerf_4view",
        sequence: str | None = None,
        train_views: list[int] | None = None,
        test_views: list[int] | None = None,
        novel_pose_views: list[int] | None = None,
        train_frames: Any = None,
        novel_pose_frames: Any = None,
        eval_frame_step: int | None = None,
        downscale: float = 1.0,
        boundary_px: int = 5,
        mask_dir: str = "auto",
        body: str | None = None,
        white_background: bool = False,
        mask_background: bool = True,
        bounds_margin: float = 0.1,
        cache_mb: float = 512.0,
        boundary_cache: str = "memory",
        cache_dir: str | None = None,
    ) -> None:
        if mask_dir not in ("auto", "mask", "mask_cihp"):
            raise ValueError(f"zju_mocap: mask_dir must be 'auto', 'mask' or 'mask_cihp', got '{mask_dir}'")
        root_path = Path(os.path.expanduser(str(root)))
        seq = ZjuSequence(root_path)
        if mask_dir != "auto" and not (root_path / mask_dir).is_dir():
            raise FileNotFoundError(
                f"zju_mocap: mask_dir='{mask_dir}' but {root_path / mask_dir} does not exist; "
                f"found {seq.available_mask_dirs() or 'no mask folder'}; use mask_dir=auto"
            )
        C = seq.num_views

        # ---- protocol
        self.sequence = sequence or sequence_key(root_path)
        views_all = list(range(C))
        preset_train_views: list[int] = views_all
        preset_train_frames: Any = None
        preset_pose_frames: Any = None
        preset_step = 1
        if protocol is not None:
            if protocol not in PROTOCOLS:
                raise ValueError(f"zju_mocap: unknown protocol '{protocol}'; known: {', '.join(PROTOCOLS)} or null")
            h36m = self.sequence is not None and self.sequence.startswith("S")
            if protocol == "aninerf_4view":
                preset_train_views = [0, 1, 2] if h36m else [0, 6, 12, 18]
            else:
                preset_train_views = [v for v in views_all if v % 6 != 3]
            preset_train_views = [v for v in preset_train_views if v < C]
            if self.sequence in PROTOCOL_FRAMES:
                b, n, step, ne, pose_begin = PROTOCOL_FRAMES[self.sequence]
                preset_train_frames = (b, b + n * step, step)
                pb = b + n * step if pose_begin is None else pose_begin
                preset_pose_frames = (pb, pb + ne * step, step)
                preset_step = EVAL_FRAME_STEP
            elif train_frames is None or (split == "novel_pose" and novel_pose_frames is None):
                raise ValueError(
                    f"zju_mocap: protocol '{protocol}' has frame numbers for {', '.join(PROTOCOL_FRAMES)} but "
                    f"{root_path} names none of them; pass sequence=<one of them>, or train_frames=[start, end, step] "
                    f"and novel_pose_frames=[start, end, step]"
                )
        pose_spec = novel_pose_frames if novel_pose_frames is not None else preset_pose_frames
        if split == "novel_pose" and pose_spec is None:
            raise ValueError(
                f"zju_mocap: split 'novel_pose' needs novel_pose_frames=[start, end, step] (or a protocol preset "
                f"that knows sequence '{self.sequence}')"
            )
        super().__init__(
            seq,
            split=split,
            train_views=list(train_views) if train_views is not None else preset_train_views,
            test_views=test_views,
            novel_pose_views=novel_pose_views,
            train_frames=train_frames if train_frames is not None else preset_train_frames,
            novel_pose_frames=pose_spec,
            eval_frame_step=int(eval_frame_step) if eval_frame_step is not None else preset_step,
            downscale=downscale,
            boundary_px=boundary_px,
            mask_dir=mask_dir,
            body=body,
            white_background=white_background,
            mask_background=mask_background,
            bounds_margin=bounds_margin,
            cache_mb=cache_mb,
            boundary_cache=boundary_cache,
            cache_dir=cache_dir,
        )
