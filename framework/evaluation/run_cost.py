"""What a trained model costs: render speed (novel view, novel pose), time per training step, Gaussian count and size.

Written into results.json at the end of training (`framework.train`), so the trade-off report
(`framework.reporting.tradeoff`) can set quality against speed and size; `framework.scene.compact` measures compact
models with the same functions.

Render speed follows tools/bench_render.py's rules (`framework.model.frame_timing`): the whole frame is timed,
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
from framework.lightning.trained_model import datamodule_for, load_module
from framework.model.frame_timing import time_frames
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
        view = FrameBatch(first.image, first.mask, first.boundary, cams.index(i % cams.num), first.frame,
                          first.pose, first.root, first.betas, first.view)  # fmt: skip
        avatar(view, sh_degree=sh_degree)

    pose_fps = 1.0 / time_frames(new_pose, warmup, repeats, device)
    view_fps = 1.0 / time_frames(new_view, warmup, repeats, device)
    return pose_fps, view_fps


def interleaved_fps(ckpts: dict[str, Path], warmup: int, repeats: int, rounds: int, device: str = "cpu",
                    rasterizer: str | None = None) -> dict[str, tuple[float, float]]:  # fmt: skip
    """(novel-pose, novel-view) fps of each checkpoint: median over `rounds` rounds, each model timed once per round
    (`render_fps` on the first split of `TIMING_SPLITS` its data has, baked weights). Why interleaved: a shared 2-core
    VM's speed drifts by 20-50 % over minutes (measured: the same model's novel-pose frame at 38 ms and, an hour
    later, at 52-67 ms), and timing the models one after the other would turn that drift into a difference between
    them (a compaction's own before/after timing read 1.34x where interleaved rounds read 1.20-1.30x).

    `rasterizer`: render every model with this backend instead of the one it was trained with (`use_rasterizer`)."""
    import statistics

    loaded = {}
    for name, path in ckpts.items():
        module = load_module(path, map_location=device)
        module.bake_weights()
        if rasterizer is not None:
            use_rasterizer(module, rasterizer)
        dm = datamodule_for(module)
        split = timing_split(dm)
        if split is None:
            raise SplatrigError(f"{path}: its data has none of the splits {TIMING_SPLITS} to time frames on.")
        loaded[name] = (module, dm, split)
    for module, dm, split in loaded.values():  # untimed: the first frames a process renders run slower
        render_fps(module, dm, split, warmup=warmup, repeats=repeats)
    times: dict[str, list[tuple[float, float]]] = {name: [] for name in loaded}
    for _ in range(rounds):
        for name, (module, dm, split) in loaded.items():
            times[name].append(render_fps(module, dm, split, warmup=warmup, repeats=repeats))
    return {name: (statistics.median(t[0] for t in ts), statistics.median(t[1] for t in ts))
            for name, ts in times.items()}  # fmt: skip


def use_rasterizer(module, name: str) -> None:
    """Render `module`'s avatar with the registered backend `name` from now on (every backend renders the same
    function, so a model trained with one renders with any; `numba` is the fast one for CPU frames)."""
    from framework.plugins import load_plugins
    from framework.registry import RASTERIZERS

    load_plugins()
    module.avatar.rasterizer = RASTERIZERS.build(name)


def run_cost(module, dm, checkpoint: Path | None, train_seconds: float, steps: int, fps_frames: int,
             fps_warmup: int = 3) -> dict[str, Any]:  # fmt: skip
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
