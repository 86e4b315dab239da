"""Dataset `synthetic_studio` (the embedded default): renders the studio sequence on first use, then reads it with the
`zju_mocap` loader — the very same code path real ZJU-MoCap data takes.

Splits: training frames are the training motions, `novel_pose` frames are the held-out motion (from `studio.json`);
test views are every `test_view_every`-th camera starting at `test_view_offset`, the rest train. The capture
imperfections (pose noise, parser masks, a skirt, ZJU framing) are `framework.data.studio` settings.
"""

from __future__ import annotations

import json
from typing import Any

from framework.data.zju.dataset import ZjuMocapDataset
from framework.registry import register


def _as_range(frames: list[int]) -> list[int]:
    """[start, end, 1] for contiguous frames (the loader reads 2- and 3-element lists as ranges), else the list."""
    if frames and frames == list(range(frames[0], frames[-1] + 1)):
        return [frames[0], frames[-1] + 1, 1]
    if len(frames) in (2, 3):
        raise ValueError(f"synthetic_studio: frames {frames} are not contiguous and would read as a range")
    return frames


@register("dataset", "synthetic_studio")
class SyntheticStudioDataset(ZjuMocapDataset):
    """The synthetic studio in the ZJU-MoCap layout; extra keyword arguments go to `zju_mocap`."""

    def __init__(
        self,
        root: str | None = None,
        split: str = "train",
        resolution: int = 512,
        views: int = 21,
        frames: int = 100,
        seed: int = 0,
        body: str = "anny",
        skeleton: str = "reduced",
        supersample: int = 1,
        motion: str = "default",
        look: str = "default",
        workers: int = 2,
        test_view_every: int = 4,
        test_view_offset: int = 2,
        eval_frame_step: int = 1,
        pose_noise_deg: float = 0.0,
        root_noise_m: float = 0.0,
        mask_error_px: float = 0.0,
        garment: str = "none",
        garment_lag: float = 0.5,
        subject_height_fraction: float | None = None,
        **zju_kwargs: Any,
    ) -> None:
        from framework.data.studio import StudioSettings, generate

        settings = StudioSettings(
            resolution=int(resolution),
            views=int(views),
            frames=int(frames),
            seed=int(seed),
            body=str(body),
            skeleton=str(skeleton),
            supersample=int(supersample),
            pose_noise_deg=float(pose_noise_deg),
            root_noise_m=float(root_noise_m),
            mask_error_px=float(mask_error_px),
            garment=str(garment),
            garment_lag=float(garment_lag),
            subject_height_fraction=None if subject_height_fraction is None else float(subject_height_fraction),
            motion=str(motion),
            look=str(look),
        )
        path = generate(settings, root, workers=int(workers), progress=True)
        meta = json.loads((path / "studio.json").read_text())
        if views < 2:
            raise ValueError(f"dataset synthetic_studio: views={views}; need at least 2 (one to train, one to test).")
        test_views = [v for v in range(views) if v % test_view_every == test_view_offset % test_view_every]
        test_views = test_views or [views - 1]
        train_views = [v for v in range(views) if v not in test_views]
        self.studio_meta = meta
        super().__init__(
            root=str(path),
            split=split,
            protocol=None,
            train_views=zju_kwargs.pop("train_views", train_views),
            test_views=zju_kwargs.pop("test_views", test_views),
            train_frames=zju_kwargs.pop("train_frames", _as_range(meta["train_frames"])),
            novel_pose_frames=zju_kwargs.pop("novel_pose_frames", _as_range(meta["novel_pose_frames"])),
            eval_frame_step=eval_frame_step,
            body=meta["body"],
            **zju_kwargs,
        )
