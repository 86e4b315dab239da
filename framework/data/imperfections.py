"""Capture imperfections for the synthetic studio: what real multi-view data gives a model to cope with.

Real sequences (ZJU-MoCap and the like) come with SMPL fits from EasyMocap and masks from a human parser (CIHP), and
both are wrong in characteristic ways. The studio renders its images from the exact mesh and then stores imperfect
annotations, so the images stay exact while the poses and masks a model is given are not:

- pose fitting noise (`perturb_poses`): every joint's rotation is turned by a random rotation whose RMS angle is the
  requested number of degrees (axis-angle noise with per-axis std = angle / sqrt(3)), and the root position moves by
  a random offset whose RMS length is the requested jitter (per-axis std = jitter / sqrt(3)); independent per frame,
  like per-frame fitting errors. The fitted mesh (vertices/) follows the noisy parameters, as a fit's mesh does.
- parser masks (`parser_like_mask`): the silhouette is moved in and out by up to `width_px` pixels, following a smooth
  random field (over- and under-segmented blobs) mixed with a zigzag (the jagged edges of a parser's output). Every
  changed pixel lies within `width_px` (+ half a pixel) of the true silhouette.
"""

from __future__ import annotations

import numpy as np


def perturb_poses(
    poses: np.ndarray, Th: np.ndarray, rotation_deg: float, root_m: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """poses [F, J, 3] axis-angle, Th [F, 3] metres -> noisy copies (float32), as described in the module docstring."""
    from scipy.spatial.transform import Rotation

    poses = np.asarray(poses, dtype=np.float64)
    Th = np.asarray(Th, dtype=np.float64)
    F, J, _ = poses.shape
    noise = rng.normal(0.0, np.deg2rad(rotation_deg) / np.sqrt(3.0), size=(F, J, 3))
    rotated = Rotation.from_rotvec(noise.reshape(-1, 3)) * Rotation.from_rotvec(poses.reshape(-1, 3))
    noisy = rotated.as_rotvec().reshape(F, J, 3)
    jitter = rng.normal(0.0, root_m / np.sqrt(3.0), size=Th.shape)
    return noisy.astype(np.float32), (Th + jitter).astype(np.float32)


def signed_distance(mask: np.ndarray) -> np.ndarray:
    """[H, W] bool -> float32 signed distance to the silhouette in pixels: > 0 inside, < 0 outside; the silhouette
    lies half a pixel from the centres of the pixels on either side of it (exact Euclidean distance transform)."""
    import cv2

    fg = np.asarray(mask, dtype=bool)
    if fg.all() or not fg.any():
        return np.full(fg.shape, np.inf if fg.all() else -np.inf, np.float32)
    inside = cv2.distanceTransform(fg.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    outside = cv2.distanceTransform((~fg).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return np.where(fg, inside - 0.5, 0.5 - outside).astype(np.float32)


def parser_like_mask(mask: np.ndarray, width_px: float, rng: np.random.Generator) -> np.ndarray:
    """[H, W] bool exact mask -> [H, W] bool mask with boundary errors of up to `width_px` pixels (see module doc)."""
    import cv2

    fg = np.asarray(mask, dtype=bool)
    if width_px <= 0 or fg.all() or not fg.any():
        return fg.copy()
    H, W = fg.shape
    # smooth field: white noise blurred over ~6 widths, scaled to unit std
    sigma = max(2.0, 6.0 * width_px)
    blobs = cv2.GaussianBlur(rng.standard_normal((H, W)).astype(np.float32), (0, 0), sigma)
    blobs /= max(float(blobs.std()), 1e-6)
    # zigzag: a triangle wave along a random direction with a period of ~3 widths, so it cuts across every boundary
    period = max(3.0, 3.0 * width_px)
    angle = rng.uniform(0, np.pi)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    phase = (xx * np.cos(angle) + yy * np.sin(angle)) / period + rng.uniform()
    zigzag = 4.0 * np.abs(phase - np.floor(phase) - 0.5) - 1.0  # in [-1, 1]
    offset = width_px * np.clip(0.6 * blobs + 0.5 * zigzag, -1.0, 1.0)  # [H, W] pixels, + erodes, - dilates
    return signed_distance(fg) > offset
