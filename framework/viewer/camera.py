"""A viser client camera (OpenCV axes: x right, y down, z forward) as our `Cameras`."""

from __future__ import annotations

import math

import torch

from framework.geometry import quat_to_rotmat
from framework.types import Cameras


def render_size(aspect: float, max_side: int) -> tuple[int, int]:
    """(width, height) with the browser canvas's aspect ratio and the longer side `max_side` pixels."""
    aspect = aspect if math.isfinite(aspect) and aspect > 0 else 1.0
    if aspect >= 1:
        return max_side, max(1, round(max_side / aspect))
    return max(1, round(max_side * aspect)), max_side


def viser_camera(wxyz, position, fov_y: float, width: int, height: int) -> Cameras:
    """viser's `P_world = [R | t] p_camera` (R from the quaternion wxyz, t = position) and vertical field of view
    (radians) -> one pinhole camera (square pixels, principal point at the image centre)."""
    R = quat_to_rotmat(torch.as_tensor(wxyz, dtype=torch.float64))  # [3, 3] camera -> world
    t = torch.as_tensor(position, dtype=torch.float64)
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = R.T
    w2c[:3, 3] = -R.T @ t
    f = 0.5 * height / math.tan(0.5 * fov_y)
    K = torch.tensor([[f, 0.0, 0.5 * width], [0.0, f, 0.5 * height], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return Cameras(K[None].float(), w2c[None].float(), int(width), int(height))
