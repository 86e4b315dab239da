"""Cameras for rendering a motion: an orbit around the subject or one of the dataset's cameras, at any resolution."""

from __future__ import annotations

import math

import torch

from framework.cameras import orbit_cameras
from framework.errors import SplatrigError
from framework.types import Cameras


def subject_view(module, dm) -> tuple[torch.Tensor, float, float]:
    """(centre [3] of the training bounds, median training-camera distance to it, horizontal field of view in
    degrees of the training cameras): how the subject was filmed, for orbits and the viewer's first view."""
    train_cams = dm.train_set.cameras
    center = torch.tensor(module.data_info["bounds"]).mean(0)
    dist = float(train_cams.centers().sub(center).norm(dim=-1).median())
    fov = 2 * math.degrees(math.atan(0.5 * train_cams.width / float(train_cams.K[0, 0, 0])))
    return center, dist, fov


def sequence_cameras(
    module, dm, mode: str, num: int, camera_index: int = 0, turns: float = 1.0, resolution: int | None = None
) -> list[Cameras]:
    """One camera per frame: `orbit` circles the subject `turns` times at the training cameras' distance and field of
    view; `fixed` is dataset camera `camera_index` for every frame. `resolution` (pixels) rescales the image size."""
    train_cams = dm.train_set.cameras
    width = resolution or train_cams.width
    height = resolution or train_cams.height
    if mode == "orbit":
        center, dist, fov = subject_view(module, dm)
        orbit = orbit_cameras(center, dist, 0.0, max(num, 1), width, height, fov_deg=fov, turns=turns)
        return [orbit.index(i) for i in range(num)]
    if mode == "fixed":
        if not 0 <= camera_index < train_cams.num:
            last = train_cams.num - 1
            raise SplatrigError(f"camera_index={camera_index}: the dataset has cameras 0..{last}; pick one of them.")
        return [train_cams.index(camera_index).resized(width, height)] * num
    raise SplatrigError(f"cameras={mode}: expected 'orbit' or 'fixed'.")
