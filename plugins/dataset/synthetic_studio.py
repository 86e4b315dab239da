"""Dataset `synthetic_studio` (the embedded default): renders the studio sequence on first use, then reads it with the
`zju_mocap` loader — the very same code path real ZJU-MoCap data takes.

Splits: training frames are the training motions, `novel_pose` frames are the held-out motion (from `studio.json`);
test views are every `test_view_every`-th camera starting at `test_view_offset`, the rest train. The capture
imperfections (pose noise, parser masks, a skirt, ZJU framing) are `framework.data.studio` settings.
"""

from __future__ import annotations

import json
from typing import Any

from framework.data.options import SequenceOptions
from framework.data.studio import StudioSettings, generate
from framework.data.zju.dataset import ZjuMocapDataset
from framework.dataset_keys import split_config
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
    """The synthetic studio in the ZJU-MoCap layout. Its config keys are its parameters (where, how many render
    processes, which cameras are held out), the `StudioSettings` fields (what is rendered: `num_views`, `num_frames`,
    resolution, motion, imperfections, ...) and the `SequenceOptions` fields (how it is read, as `zju_mocap`)."""

    config_schemas = (StudioSettings, SequenceOptions)  # `body` is the studio's: the sequence is posed with it

    def __init__(
        self,
        root: str | None = None,
        split: str = "train",
        workers: int = 2,
        test_view_every: int = 4,
        test_view_offset: int = 2,
        params_dir: str = "auto",
        vertices_dir: str = "auto",
        **config: Any,
    ) -> None:
        studio, options = split_config(config, *self.config_schemas, dataset="synthetic_studio")
        settings = StudioSettings(**studio)
        path = generate(settings, root, workers=int(workers), progress=True)
        meta = json.loads((path / "studio.json").read_text())
        n = settings.num_views
        if n < 2:
            raise ValueError(f"dataset synthetic_studio: num_views={n}; need at least 2 (one to train, one to test).")
        test_views = [v for v in range(n) if v % test_view_every == test_view_offset % test_view_every] or [n - 1]
        self.studio_meta = meta
        layout = {
            "train_views": [v for v in range(n) if v not in test_views],
            "test_views": test_views,
            "train_frames": _as_range(meta["train_frames"]),
            "novel_pose_frames": _as_range(meta["novel_pose_frames"]),
        }
        # keys the config gives win over the studio's split; the body is the one the sequence was posed with
        folders = {"params_dir": params_dir, "vertices_dir": vertices_dir}
        super().__init__(
            root=str(path), split=split, protocol=None, **folders, **{**layout, **options, "body": meta["body"]}
        )
