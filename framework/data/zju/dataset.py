"""The training dataset of a ZJU-MoCap-layout sequence (ZJU-MoCap, H36M and CMU Panoptic in the Neural Body /
Animatable NeRF layout, and the synthetic studio, written in the same layout). The layout is documented in
`framework.data.zju.layout`, the protocols in `framework.data.zju.protocols`.

Samples, images, masks, boundary masks, cameras, body parameters and bounds follow the conventions shared with every
sequence reader (`framework.data.sequence_dataset`): stored K/D/R/T with T in millimetres, undistortion keeping K,
area downscaling, root = [[R(Rh), Th], [0, 1]]. Explicit arguments always override the protocol preset's values.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from framework.data.sequence_dataset import SequenceDataset
from framework.data.zju.layout import ZjuMissingFileError
from framework.data.zju.protocols import PROTOCOL_FRAMES, protocol_preset, sequence_key
from framework.data.zju.reader import ZjuSequence

__all__ = ["ZjuMocapDataset"]


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
        boundary_ref_side: int | None = None,
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
            raise ZjuMissingFileError(
                f"zju_mocap: mask_dir='{mask_dir}' but {root_path / mask_dir} does not exist; "
                f"found {seq.available_mask_dirs() or 'no mask folder'}; use mask_dir=auto"
            )
        C = seq.num_views

        # ---- protocol
        self.sequence = sequence or sequence_key(root_path)
        preset = protocol_preset(protocol, self.sequence, C)
        if (
            protocol is not None
            and preset.train_frames is None
            and (train_frames is None or (split == "novel_pose" and novel_pose_frames is None))
        ):
            raise ValueError(
                f"zju_mocap: protocol '{protocol}' has frame numbers for {', '.join(PROTOCOL_FRAMES)} but "
                f"{root_path} names none of them; pass sequence=<one of them>, or train_frames=[start, end, step] "
                f"and novel_pose_frames=[start, end, step]"
            )
        preset_train_views, preset_train_frames = preset.train_views, preset.train_frames
        preset_pose_frames, preset_step = preset.novel_pose_frames, preset.eval_frame_step
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
            boundary_ref_side=boundary_ref_side,
            mask_dir=mask_dir,
            body=body,
            white_background=white_background,
            mask_background=mask_background,
            bounds_margin=bounds_margin,
            cache_mb=cache_mb,
            boundary_cache=boundary_cache,
            cache_dir=cache_dir,
        )
