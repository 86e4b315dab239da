"""The training dataset of a ZJU-MoCap-layout sequence (ZJU-MoCap, H36M and CMU Panoptic in the Neural Body /
Animatable NeRF layout, and the synthetic studio, written in the same layout). The layout is documented in
`framework.data.zju.layout`, the protocols in `framework.data.zju.protocols`.

Samples, images, masks, boundary masks, cameras, body parameters and bounds follow the conventions shared with every
sequence reader (`framework.data.sequence_dataset`): stored K/D/R/T with T in millimetres, undistortion keeping K,
area downscaling, root = [[R(Rh), Th], [0, 1]]. Explicit options always override the protocol preset's values.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from framework.data.options import SequenceOptions
from framework.data.sequence_dataset import SequenceDataset
from framework.data.zju.layout import ZjuMissingFileError
from framework.data.zju.protocols import PROTOCOL_FRAMES, protocol_preset, sequence_key
from framework.data.zju.reader import ZjuSequence

__all__ = ["ZjuMocapDataset"]


class ZjuMocapDataset(SequenceDataset):
    """One split of a ZJU-MoCap-layout sequence; see the module docstring for conventions and protocols.

    `root`, `protocol`, `sequence`, `params_dir` and `vertices_dir` are the layout's own keys; every other key is a
    `SequenceOptions` field (views, frames, images, caches); the protocol fills in what it leaves null."""

    def __init__(
        self,
        root: str,
        split: str = "train",
        protocol: str | None = "aninerf_4view",
        sequence: str | None = None,
        params_dir: str = "auto",
        vertices_dir: str = "auto",
        **options: Any,
    ) -> None:
        opts = SequenceOptions.from_config(options, "zju_mocap")
        if opts.mask_dir not in ("auto", "mask", "mask_cihp"):
            raise ValueError(f"zju_mocap: mask_dir must be 'auto', 'mask' or 'mask_cihp', got '{opts.mask_dir}'")
        root_path = Path(os.path.expanduser(str(root)))
        seq = ZjuSequence(root_path, params_dir=params_dir, vertices_dir=vertices_dir)
        if opts.mask_dir != "auto" and not (root_path / opts.mask_dir).is_dir():
            raise ZjuMissingFileError(
                f"zju_mocap: mask_dir='{opts.mask_dir}' but {root_path / opts.mask_dir} does not exist; "
                f"found {seq.available_mask_dirs() or 'no mask folder'}; use mask_dir=auto"
            )

        # ---- protocol
        self.sequence = sequence or sequence_key(root_path)
        preset = protocol_preset(protocol, self.sequence, seq.num_views)
        if (
            protocol is not None
            and preset.train_frames is None
            and (opts.train_frames is None or (split == "novel_pose" and opts.novel_pose_frames is None))
        ):
            raise ValueError(
                f"zju_mocap: protocol '{protocol}' has frame numbers for {', '.join(PROTOCOL_FRAMES)} but "
                f"{root_path} names none of them; pass sequence=<one of them>, or train_frames=[start, end, step] "
                f"and novel_pose_frames=[start, end, step]"
            )
        opts = opts.with_defaults(
            train_views=preset.train_views,
            train_frames=preset.train_frames,
            novel_pose_frames=preset.novel_pose_frames,
            eval_frame_step=preset.eval_frame_step,
        )
        if split == "novel_pose" and opts.novel_pose_frames is None:
            raise ValueError(
                f"zju_mocap: split 'novel_pose' needs novel_pose_frames=[start, end, step] (or a protocol preset "
                f"that knows sequence '{self.sequence}')"
            )
        super().__init__(seq, split=split, options=opts)
