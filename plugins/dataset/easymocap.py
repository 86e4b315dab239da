"""Dataset `easymocap`: a capture as EasyMocap leaves it (intri.yml / extri.yml, images/<cam>/, mask/ or mask-schp/,
output*/smpl/*.json), read directly; the layout and EasyMocap's conventions are in `framework.data.easymocap_layout`.

Samples, undistortion, downscaling, masks, boundary masks, caches and body parameters are the ZJU-MoCap reader's
(`framework.data.sequence_dataset`), so the same capture gives the same batches in either layout. There is no
protocol: views and frames are chosen explicitly.
- Views: indices into the camera list (intri.yml's order, or `cameras`), or camera names. `train_views` defaults to
  every camera not in `test_views`; `test_views` defaults to the cameras not trained on (camera 0 when that leaves
  none, as the ZJU reader); `novel_pose_views` to the test views.
- Frames: positions in the sorted list of image stems; `train_frames` / `novel_pose_frames` are [start, end, step]
  (end exclusive) or lists; evaluation splits take every `eval_frame_step`-th frame.
- Body: "smpl" for 72 pose values, "smplx" for 87 (hand PCA, expanded with `body_model_path`'s SMPL-X file) or 165;
  other counts need `body=` (e.g. a procedural test body).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from framework.data.easymocap_layout import EasyMocapSequence
from framework.data.options import SequenceOptions
from framework.data.sequence_dataset import SequenceDataset
from framework.registry import register

_ANNOUNCED: set[tuple[str, str]] = set()


def view_indices(views: Sequence[int | str] | None, names: list[str], what: str) -> list[int] | None:
    """Camera names or indices -> indices (None stays None); names win when a value is both."""
    if views is None:
        return None
    out = []
    for v in views:
        if isinstance(v, str):
            if v not in names:
                raise ValueError(f"easymocap: {what} names camera '{v}' but the cameras are {names}")
            out.append(names.index(v))
        else:
            out.append(int(v))
    return out


@register("dataset", "easymocap")
class EasyMocapDataset(SequenceDataset):
    """One split of an EasyMocap capture; see the module docstring.

    The layout's own keys are its parameters (which cameras, parameter and vertex folders, person, the SMPL-X file for
    hand-PCA poses); every other key is a `SequenceOptions` field, views given as indices or camera names."""

    def __init__(
        self,
        root: str,
        split: str = "train",
        cameras: list[str] | None = None,
        params_dir: str = "auto",
        vertices_dir: str | None = "auto",
        person_id: int | None = None,
        body_model_path: str | None = None,
        body_gender: str = "neutral",
        **options: Any,
    ) -> None:
        opts = SequenceOptions.from_config(options, "easymocap")
        seq = EasyMocapSequence(
            Path(os.path.expanduser(str(root))),
            cameras=None if cameras is None else [str(c) for c in cameras],
            mask_dir=opts.mask_dir,
            params_dir=params_dir,
            vertices_dir=vertices_dir,
            person_id=person_id,
            smplx_model_path=body_model_path,
            smplx_gender=body_gender,
        )
        self.mask_source = seq.mask_dir
        key = (str(seq.root), seq.mask_dir)
        if key not in _ANNOUNCED:
            _ANNOUNCED.add(key)
            others = [d for d in seq.available_mask_dirs() if d != seq.mask_dir]
            also = f" ({', '.join(others)}/ also present; data.mask_dir picks)" if others else ""
            print(
                f"[splatrig] easymocap: masks from {seq.mask_dir}/{also}, parameters from "
                f"{seq.params_dir.relative_to(seq.root)}/",
                file=sys.stderr,
            )
        names = seq.camera_names
        test = view_indices(opts.test_views, names, "test_views")
        train = view_indices(opts.train_views, names, "train_views")
        if train is None:
            train = [v for v in range(seq.num_views) if test is None or v not in test] or list(range(seq.num_views))
        opts = replace(
            opts,
            train_views=train,
            test_views=test,
            novel_pose_views=view_indices(opts.novel_pose_views, names, "novel_pose_views"),
            mask_dir=seq.mask_dir,
        )
        super().__init__(seq, split=split, options=opts)
