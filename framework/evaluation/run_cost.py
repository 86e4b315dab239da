"""What a trained model costs: render speed (novel view, novel pose), time per training step, Gaussian count and size.

Written into results.json at the end of training (`framework.train`), so the trade-off report
(`framework.reporting.tradeoff`) can set quality against speed and size; `framework.compaction.compact` measures compact
models with the same functions.

Render speed follows tools/bench_render.py's rules (`framework.evaluation.frame_timing`): the whole frame is timed,
synchronised on CUDA, median of `repeats` frames after `warmup`; the real-time path uses baked blend weights (the
caller bakes them first). Novel pose: a new pose every frame (F_a correction + LBS + rasterisation), the frames of the
novel-pose split; novel view: one pose from changing cameras of the same split (the posed Gaussians are cached, so
only rasterisation runs).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from framework.errors import SplatrigError
from framework.evaluation.frame_timing import time_frames
from framework.types import FrameBatch

TIMING_SPLITS = ("novel_pose", "novel_view")  # the first one the dataset has is timed


def model_bytes(module) -> int:
    """Bytes of the learned tensors: Gaussians, networks, pose refinement (the body mesh buffers are left out)."""
    return sum(t.numel() * t.element_size() for k, t in module.state_dict().items() if not k.startswith("avatar.body."))


def distinct_frame_items(dataset, limit: int) -> list[int]:
    """Item indices of up to `limit` different frames, spread over the split (one view each)."""
    seen: dict[int, int] = {}
    for i in range(len(dataset)):
        frame = dataset.sample(i)[0]
        seen.setdefault(frame, i)
    items = list(seen.values())
    step = max(1, len(items) // max(limit, 1))
    return items[::step][:limit]


def timing_split(dm, splits: tuple[str, ...] = TIMING_SPLITS) -> str | None:
    """The first of `splits` the data module can build, or None."""
    for split in splits:
        try:
            dm.split(split)
        except SplatrigError:
            continue
        return split
    return None


@torch.no_grad()
def render_fps(module, dm, split: str, warmup: int = 3, repeats: int = 10) -> tuple[float, float]:
    """(novel-pose fps, novel-view fps) of `module`'s avatar on the frames and cameras of `split`."""
    module.eval()
    device = module.device
    dataset = dm.split(split)
    batches = [dataset[i].to(device) for i in distinct_frame_items(dataset, warmup + repeats)]
    if len(batches) < 2:  # a tiny split: borrow poses from the training frames (any two poses differ)
        train = dm.train_set
        batches += [train[i].to(device) for i in distinct_frame_items(train, warmup + repeats)]
    sh_degree = module.sh_degree(module.trained_steps())
    avatar = module.avatar

    def new_pose(i: int) -> None:  # consecutive frames differ, so the posed-Gaussian cache never answers
        avatar(batches[i % len(batches)], sh_degree=sh_degree)

    cams = dataset.cameras.to(device)
    first = batches[0]

    def new_view(i: int) -> None:
        view = FrameBatch(
            first.image,
            first.mask,
            first.boundary,
            cams.index(i % cams.num),
            first.frame,
            first.pose,
            first.root,
            first.betas,
            first.view,
        )
        avatar(view, sh_degree=sh_degree)

    pose_fps = 1.0 / time_frames(new_pose, warmup, repeats, device)
    view_fps = 1.0 / time_frames(new_view, warmup, repeats, device)
    return pose_fps, view_fps


def use_rasterizer(module, name: str) -> None:
    """Render `module`'s avatar with the registered backend `name` from now on (every backend renders the same
    function, so a model trained with one renders with any; `numba` is the fast one for CPU frames)."""
    from framework.plugins import load_plugins
    from framework.registry import RASTERIZERS

    load_plugins()
    module.avatar.rasterizer = RASTERIZERS.build(name)


def run_cost(
    module, dm, checkpoint: Path | None, train_seconds: float, steps: int, fps_frames: int, fps_warmup: int = 3
) -> dict[str, Any]:
    """The results.json fields of a run's cost (see `framework.evaluation.run_record`); fps are skipped (None) when
    `fps_frames` is 0 or the data has no held-out split, and novel-pose fps when the model has no body to pose."""
    pose_fps = view_fps = None
    split = timing_split(dm) if fps_frames > 0 else None
    if split is not None:
        pose_fps, view_fps = render_fps(module, dm, split, warmup=fps_warmup, repeats=fps_frames)
        if module.avatar.body is None:
            pose_fps = None
    return {
        "seconds_per_step": round(train_seconds / steps, 4) if steps > 0 else None,
        "render_fps": {
            "novel_pose": None if pose_fps is None else round(pose_fps, 2),
            "novel_view": None if view_fps is None else round(view_fps, 2),
            "split": split,
            "frames": int(fps_frames) if split is not None else 0,
            "warmup": int(fps_warmup),
            "device": str(module.device),
        },
        "model_bytes": model_bytes(module),
        "checkpoint_bytes": None if checkpoint is None or not checkpoint.is_file() else checkpoint.stat().st_size,
        "checkpoint": None if checkpoint is None else checkpoint.name,
    }
