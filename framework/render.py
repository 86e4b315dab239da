"""`python -m framework.render ckpt=... motion=... cameras=...`: a novel-pose video (MP4 + PNG frames)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from framework.cameras import orbit_cameras
from framework.errors import SplatrigError, reported_as_message
from framework.types import Cameras, FrameBatch


def load_motion(module, dm, motion: str) -> tuple[torch.Tensor, torch.Tensor | None, list[int]]:
    """Poses [F, J, 3], roots [F, 4, 4] or None, and the frame ids (for pose-refinement lookups; -1 = none)."""
    path = Path(motion)
    if path.suffix in (".npz", ".npy"):
        if not path.is_file():
            raise SplatrigError(f"motion={motion}: file not found. Give a .npz with `poses` [F, J, 3] "
                                f"(and optionally `roots` [F, 4, 4]) or a split name (novel_pose, train).")  # fmt: skip
        try:
            data = np.load(path)
        except (OSError, ValueError) as exc:
            why = type(exc).__name__
            raise SplatrigError(f"motion={motion}: cannot be read as a numpy file ({why}); give a .npz with `poses` "
                                f"[F, J, 3] (and optionally `roots` [F, 4, 4]).") from None  # fmt: skip
        if path.suffix == ".npz" and "poses" not in data:
            raise SplatrigError(f"motion={motion}: the .npz holds {sorted(data.files)} but no `poses` [F, J, 3]; "
                                f"save the joint rotations under the key `poses`.")  # fmt: skip
        poses = torch.as_tensor(data["poses"] if path.suffix == ".npz" else data, dtype=torch.float32)
        roots = torch.as_tensor(data["roots"], dtype=torch.float32) if path.suffix == ".npz" and "roots" in data \
            else None  # fmt: skip
        body = module.avatar.body
        if body is not None and (poses.ndim != 3 or poses.shape[1:] != (body.num_joints, 3)):
            raise SplatrigError(f"motion={motion}: poses have shape {tuple(poses.shape)}, expected "
                                f"[F, {body.num_joints}, 3] for body '{module.cfg['body']['name']}'.")  # fmt: skip
        for name, values in (("poses", poses), ("roots", roots)):
            if values is not None and not bool(torch.isfinite(values).all()):
                frame = int((~torch.isfinite(values.flatten(1))).any(1).nonzero()[0])
                raise SplatrigError(f"motion={motion}: `{name}` of frame {frame} holds a non-finite value; expected "
                                    f"finite numbers (re-export the motion or drop that frame).")  # fmt: skip
        return poses, roots, [-1] * poses.shape[0]
    dataset = dm.split(motion)
    all_poses = dataset.poses()
    if all_poses is None:
        raise SplatrigError(f"motion={motion}: this model has no body (a static scene); render it with a split "
                            f"of views instead of a motion.")  # fmt: skip
    frames = list(dataset.frame_ids)
    roots = dataset.roots()[frames] if hasattr(dataset, "roots") else None
    return all_poses[frames], roots, frames


@torch.no_grad()
def render_sequence(module, dm, motion: str, cameras: str, camera_index: int, turns: float, resolution: int | None,
                    max_frames: int | None) -> list[np.ndarray]:  # fmt: skip
    poses, roots, frames = load_motion(module, dm, motion)
    if max_frames:
        poses, frames = poses[:max_frames], frames[:max_frames]
        roots = None if roots is None else roots[:max_frames]
    train_cams = dm.train_set.cameras
    width = resolution or train_cams.width
    height = resolution or train_cams.height
    n = poses.shape[0]
    if cameras == "orbit":
        bounds = torch.tensor(module.data_info["bounds"])
        center = bounds.mean(0)
        dist = float(train_cams.centers().sub(center).norm(dim=-1).median())
        fov = 2 * math.degrees(math.atan(0.5 * train_cams.width / float(train_cams.K[0, 0, 0])))
        orbit = orbit_cameras(center, dist, 0.0, max(n, 1), width, height, fov_deg=fov, turns=turns)
        cams = [orbit.index(i) for i in range(n)]
    elif cameras == "fixed":
        if not 0 <= camera_index < train_cams.num:
            raise SplatrigError(f"camera_index={camera_index}: the training rig has cameras 0..{train_cams.num - 1}; "
                                f"pick one of them.")  # fmt: skip
        scale = width / train_cams.width
        K = train_cams.K[camera_index : camera_index + 1].clone()
        K[:, :2] *= scale
        cam = Cameras(K, train_cams.world_to_cam[camera_index : camera_index + 1], width, height)
        cams = [cam] * n
    else:
        raise SplatrigError(f"cameras={cameras}: expected 'orbit' or 'fixed'.")
    images = []
    device = module.device
    for i in tqdm(range(n), desc="rendering", unit="frame"):
        cam = cams[i].to(device)
        batch = FrameBatch(
            image=torch.zeros(1, cam.height, cam.width, 3, device=device),
            mask=torch.zeros(1, cam.height, cam.width, device=device),
            boundary=torch.ones(1, cam.height, cam.width, device=device),
            cameras=cam,
            frame=torch.tensor([max(frames[i], 0)], device=device),
            pose=poses[i : i + 1].to(device),
            root=None if roots is None else roots[i : i + 1].to(device),
        )
        rgb = module.render_batch(batch).render.rgb[0].clamp(0, 1)
        images.append((rgb.cpu().numpy() * 255).round().astype(np.uint8))
    return images


def main() -> int:
    import hydra
    from omegaconf import DictConfig

    @hydra.main(version_base="1.3", config_path="pkg://framework.conf", config_name="render")
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
    from framework.evaluate import datamodule_for, load_module

    check_render_config(cfg)
    module = load_module(cfg.ckpt)
    module.eval()
    dm = datamodule_for(module)
    images = render_sequence(module, dm, str(cfg.motion), str(cfg.cameras), int(cfg.camera_index),
                             float(cfg.orbit_turns), cfg.resolution, cfg.max_frames)  # fmt: skip
    name = f"render_{Path(str(cfg.motion)).stem}_{cfg.cameras}"
    out = Path(cfg.out_dir) if cfg.out_dir else Path(cfg.ckpt).resolve().parent.parent / name
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
