"""Camera construction: look-at views and orbits around a subject (OpenCV: x right, y down, z forward)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from framework.types import Cameras


def look_at(eye: Tensor, target: Tensor, up: Tensor) -> Tensor:
    """World-to-camera [4, 4] for a camera at `eye` looking at `target`; `up` is the world's up direction."""
    forward = target - eye
    forward = forward / forward.norm()
    right = torch.linalg.cross(forward, up)
    if right.norm() < 1e-8:  # looking straight along `up`: any perpendicular will do
        right = torch.linalg.cross(forward, torch.tensor([1.0, 0.0, 0.0], dtype=eye.dtype))
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    R = torch.stack([right, down, forward])  # rows: camera axes in world coordinates
    w2c = torch.eye(4, dtype=eye.dtype)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    return w2c


def orbit_cameras(
    center: Tensor,
    radius: float,
    height: float,
    num: int,
    width: int,
    height_px: int,
    fov_deg: float = 40.0,
    up: tuple[float, float, float] = (0.0, 0.0, 1.0),
    start_deg: float = 0.0,
    turns: float = 1.0,
) -> Cameras:
    """`num` cameras evenly spaced over `turns` circles around `center` (horizontal), all looking at it."""
    up_t = torch.tensor(up, dtype=torch.float32)
    up_t = up_t / up_t.norm()
    # two horizontal axes perpendicular to `up`
    a = torch.linalg.cross(up_t, torch.tensor([0.0, 1.0, 0.0]) if abs(up_t[1]) < 0.9 else torch.tensor([1.0, 0, 0]))
    a = a / a.norm()
    b = torch.linalg.cross(up_t, a)
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    K = torch.tensor([[f, 0, width / 2], [0, f, height_px / 2], [0, 0, 1]], dtype=torch.float32)
    w2c = []
    for i in range(num):
        t = math.radians(start_deg) + 2 * math.pi * turns * i / num
        eye = center + radius * (math.cos(t) * a + math.sin(t) * b) + height * up_t
        w2c.append(look_at(eye, center, up_t))
    return Cameras(K=K.expand(num, 3, 3).clone(), world_to_cam=torch.stack(w2c), width=width, height=height_px)
