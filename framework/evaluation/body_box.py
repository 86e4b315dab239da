"""The body-box protocol of Neural Body / Animatable NeRF: metrics inside the image of the subject's 3D bounding box.

Why: a whole-image metric is dominated by background pixels a model gets right for free, which hides differences on
the body. The protocol most peers report (zju3dv/neuralbody `lib/evaluators/if_nerf.py`, the same in
animatable_nerf): take the world-space box of the frame's posed body vertices grown by 5 cm, project its 8 corners
and fill its 6 faces (their union: the convex hull of the projected corners) to get `mask_at_box`; PSNR over the
pixels inside that mask; SSIM (and LPIPS, as later peers do) on the bounding rectangle of the mask, with the pixels
outside the mask set to 0 in both images.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch
from torch import Tensor

BOX_MARGIN_M = 0.05  # Neural Body grows the vertex box by 5 cm on every side
#: metrics that average over pixels: evaluated on the pixels inside the box; all others on its bounding rectangle
PIXELWISE_METRICS = ("psnr",)


def box_corners(bounds: np.ndarray) -> np.ndarray:
    """bounds [2, 3] (min, max) -> corners [8, 3]; corner i takes max on axis a when bit a of i is set."""
    lo, hi = np.asarray(bounds, dtype=np.float64)
    return np.array([[(hi if (i >> a) & 1 else lo)[a] for a in range(3)] for i in range(8)])


def box_mask(bounds: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray, width: int, height: int) -> np.ndarray:
    """[H, W] bool: the pixels whose centres fall in the image of the box.

    The image of a box in front of the camera is the convex hull of its 8 projected corners (Neural Body fills the 6
    projected faces, whose union is that hull); a pixel is in it when its centre is on the inner side of every hull
    edge. K in our pixel convention (pixel (i, j) has its centre at (j + 0.5, i + 0.5))."""
    import cv2

    corners = box_corners(bounds)
    cam = corners @ np.asarray(world_to_cam)[:3, :3].T + np.asarray(world_to_cam)[:3, 3]  # [8, 3]
    if (cam[:, 2] <= 0).any():
        raise ValueError(
            "body box: a corner of the box is behind the camera; the protocol needs the whole box in front."
        )
    uv = cam @ np.asarray(K).T
    xy = uv[:, :2] / uv[:, 2:]  # [8, 2] image coordinates
    hull = cv2.convexHull(xy.astype(np.float32)).reshape(-1, 2).astype(np.float64)  # [M, 2], in order
    nxt = np.roll(hull, -1, axis=0)
    orientation = np.sign(np.sum(hull[:, 0] * nxt[:, 1] - nxt[:, 0] * hull[:, 1]))
    px, py = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)  # [H, W] pixel centres
    inside = np.ones((height, width), bool)
    for (ax, ay), (bx, by) in zip(hull, nxt, strict=True):
        inside &= orientation * ((bx - ax) * (py - ay) - (by - ay) * (px - ax)) >= 0
    return inside


def frame_box(vertices: np.ndarray, margin: float = BOX_MARGIN_M) -> np.ndarray:
    """Posed world vertices [V, 3] -> the protocol's box [2, 3]."""
    v = np.asarray(vertices, dtype=np.float64)
    return np.stack([v.min(0) - margin, v.max(0) + margin])


def box_region_metrics(pred: Tensor, target: Tensor, mask: np.ndarray, metrics: Mapping[str, object]) -> dict:
    """pred, target [H, W, 3] in [0, 1]; mask [H, W] bool -> {metric name: value} inside the body box.

    Pixel-averaging metrics (PSNR) see the pixels inside the mask as a [1, 1, P, 3] image; every other metric the
    mask's bounding rectangle with the outside zeroed in both images. A rectangle smaller than a metric accepts
    (e.g. SSIM's 11-pixel window) gives NaN for that metric."""
    import cv2

    out: dict[str, float] = {}
    m = torch.as_tensor(mask, device=pred.device)
    if not m.any():
        return {name: float("nan") for name in metrics}
    x, y, w, h = cv2.boundingRect(np.asarray(mask, dtype=np.uint8))
    keep = m[..., None].to(pred.dtype)
    crop_pred = (pred * keep)[y : y + h, x : x + w][None]  # [1, h, w, 3]
    crop_target = (target * keep)[y : y + h, x : x + w][None]
    for name, metric in metrics.items():
        if name in PIXELWISE_METRICS:
            out[name] = float(metric(pred[m][None, None], target[m][None, None])[0])
            continue
        try:
            out[name] = float(metric(crop_pred, crop_target)[0])
        except ValueError:  # the crop is too small for this metric
            out[name] = float("nan")
    return out
