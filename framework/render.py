"""`python -m framework.render ckpt=... motion=... cameras=...`: a video (MP4 + PNG frames) of the avatar moving.

`motion` is a split of the training data (`novel_pose`, `train`) or a motion file: our pose files, an AMASS-layout
SMPL-family .npz, or a .bvh (retargeted onto the avatar and resampled to `fps`; framework.data.motion_files).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from framework.errors import reported_as_message
from framework.paths import beside_checkpoint


@torch.no_grad()
def render_sequence(
    module,
    dm,
    motion: str,
    cameras: str,
    camera_index: int,
    turns: float,
    resolution: int | None,
    max_frames: int | None,
    fps: float | None = None,
) -> list[np.ndarray]:
    """uint8 frames [H, W, 3] of `motion` (a split or a file, resampled to `fps`) seen by `cameras`."""
    from framework.animation.camera_paths import sequence_cameras
    from framework.animation.frames import render_rgb, to_uint8
    from framework.animation.sources import load_motion

    clip, frames = load_motion(module, dm, motion, fps)
    clip = clip.head(max_frames)
    n = clip.num_frames
    cams = sequence_cameras(module, dm, cameras, n, camera_index, turns, resolution)
    images = []
    for i in tqdm(range(n), desc="rendering", unit="frame"):
        root = None if clip.roots is None else torch.as_tensor(clip.roots[i])
        rgb = render_rgb(module, cams[i], torch.as_tensor(clip.poses[i]), root, frames[i])
        images.append(to_uint8(rgb[0]))
    return images


def main() -> int:
    from omegaconf import DictConfig

    from framework.cli import hydra_main

    @hydra_main("render")
    def _main(cfg: DictConfig) -> None:
        with reported_as_message():
            render_from_config(cfg)

    _main()
    return 0


def render_from_config(cfg) -> Path:
    """What `python -m framework.render` does with its composed config; returns the output folder. Every file is
    written atomically (a rerun after an interruption never finds a half-written frame or video)."""
    import imageio.v3 as iio

    from framework.atomic import atomic_path
    from framework.config_checks import check_render_config
    from framework.lightning.trained_model import data_overrides, datamodule_for, load_module

    check_render_config(cfg)
    module = load_module(cfg.ckpt)
    module.eval()
    dm = datamodule_for(module, data_overrides(cfg))
    images = render_sequence(
        module,
        dm,
        str(cfg.motion),
        str(cfg.cameras),
        int(cfg.camera_index),
        float(cfg.orbit_turns),
        cfg.resolution,
        cfg.max_frames,
        float(cfg.fps),
    )
    name = f"render_{Path(str(cfg.motion)).stem}_{cfg.cameras}"
    out = Path(cfg.out_dir) if cfg.out_dir else beside_checkpoint(cfg.ckpt, name)
    (out / "frames").mkdir(parents=True, exist_ok=True)
    for i, img in enumerate(images):
        with atomic_path(out / "frames" / f"{i:05d}.png") as tmp:
            iio.imwrite(tmp, img)
    video = out / f"{name}.mp4"
    with atomic_path(video) as tmp:
        iio.imwrite(tmp, np.stack(images), fps=int(cfg.fps), codec="libx264", macro_block_size=1)
    print(f"[splatrig] wrote {len(images)} frames to {out / 'frames'} and {video}")
    return out


if __name__ == "__main__":
    main()
