"""One posed frame of a loaded avatar: the FrameBatch it needs, its posed Gaussians, its render."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from framework.types import Cameras, FrameBatch, Gaussians

NO_FRAME = -1  # frame id of a pose from outside the training sequence (no per-frame pose refinement)


def frame_batch(cameras: Cameras, pose: Tensor | None, root: Tensor | None, frame: int = NO_FRAME) -> FrameBatch:
    """A FrameBatch for rendering only: pose [J, 3], root [4, 4] (or None), empty images, on the cameras' device."""
    device = cameras.device
    C, H, W = cameras.num, cameras.height, cameras.width
    return FrameBatch(
        image=torch.zeros(C, H, W, 3, device=device),
        mask=torch.zeros(C, H, W, device=device),
        boundary=torch.ones(C, H, W, device=device),
        cameras=cameras,
        frame=torch.full((C,), int(frame), dtype=torch.long, device=device),
        pose=None if pose is None else pose.to(device, torch.float32).expand(C, -1, -1),
        root=None if root is None else root.to(device, torch.float32).expand(C, -1, -1),
    )


def point_camera(device: torch.device | str = "cpu") -> Cameras:
    """A 1x1 camera, for calls that need a batch but draw nothing (posing, bone transforms)."""
    return Cameras(torch.eye(3, device=device)[None], torch.eye(4, device=device)[None], 1, 1)


@torch.no_grad()
def posed_gaussians(module, pose: Tensor | None, root: Tensor | None, frame: int = NO_FRAME) -> Gaussians:
    """The corrected, skinned world-space Gaussians the rasterizer receives for this pose."""
    batch = frame_batch(point_camera(module.device), pose, root, frame)
    return module.avatar.pose(batch)[1]


@torch.no_grad()
def render_rgb(module, cameras: Cameras, pose: Tensor | None, root: Tensor | None, frame: int = NO_FRAME) -> Tensor:
    """[C, H, W, 3] float colours in [0, 1] of the avatar at this pose (the training/evaluation render path)."""
    batch = frame_batch(cameras.to(module.device), pose, root, frame)
    return module.render_batch(batch).render.rgb.clamp(0, 1)


def to_uint8(rgb: Tensor) -> np.ndarray:
    """[H, W, 3] float in [0, 1] -> uint8 numpy."""
    return (rgb.detach().cpu().numpy() * 255).round().astype(np.uint8)
