"""The boundary mask M_b: 0 within n pixels of the silhouette, 1 elsewhere.

Mask edges are where segmentation (and our rendered alpha) is least trustworthy, so losses down-weight a band around
them. Definition used here, checked by a brute-force test: pixel p is in the band (M_b = 0) when some pixel q of the
opposite label lies within Euclidean distance n of p, i.e. |p - q| <= n between pixel centres. For n = 0 the band is
empty. Pixels outside the image do not count as either label (an image border is not a silhouette).

Its half-width is a length in the image: the paper's n = 5 is at 512 px, and the same band at another size is
n = max(1, round(5 * side / 512)) (`scaled_half_width`), so M_b covers the same share of the body at every resolution.
"""

from __future__ import annotations

import numpy as np


def scaled_half_width(n: int, side: int, ref_side: int | None) -> int:
    """The band's half-width in pixels of an image whose shorter side is `side`, for `n` pixels at `ref_side`:
    max(1, round(n * side / ref_side)) (halves up), 0 when n is 0 (no band); `ref_side` None keeps n as it is."""
    if n < 0 or (ref_side is not None and ref_side <= 0):
        raise ValueError(f"boundary band: expected n >= 0 and ref_side > 0, got n={n}, ref_side={ref_side}.")
    if ref_side is None or n == 0:
        return int(n)
    return max(1, int(n * side / ref_side + 0.5))


def _disk(n: int) -> np.ndarray:
    r = np.arange(-n, n + 1)
    return ((r[:, None] ** 2 + r[None, :] ** 2) <= n * n).astype(np.uint8)  # [2n+1, 2n+1]


def boundary_mask(mask: np.ndarray, n: int = 5) -> np.ndarray:
    """mask [H, W] (foreground non-zero) -> float32 [H, W], 0 within `n` px of the silhouette, 1 elsewhere.

    dilate(fg) marks background pixels within n of the foreground, dilate(bg) foreground pixels within n of the
    background; their intersection is exactly the band (a disk structuring element gives Euclidean distance).
    """
    import cv2

    fg = (np.asarray(mask) != 0).astype(np.uint8)
    if fg.ndim != 2:
        raise ValueError(f"boundary_mask: expected a [H, W] mask, got shape {fg.shape}")
    if n <= 0 or fg.size == 0:
        return np.ones(fg.shape, dtype=np.float32)
    kernel = _disk(int(n))
    # Border pixels must not be treated as either label: pad with the value that cannot create a band.
    near_fg = cv2.dilate(fg, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    near_bg = cv2.dilate(1 - fg, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    band = (near_fg & near_bg).astype(bool)
    return (~band).astype(np.float32)


def boundary_mask_bruteforce(mask: np.ndarray, n: int = 5) -> np.ndarray:
    """O(H^2 W^2) reference of `boundary_mask` (small masks only): the distance to the nearest pixel of the other
    label, computed directly."""
    fg = np.asarray(mask) != 0
    H, W = fg.shape
    ii, jj = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    pts = np.stack([ii.ravel(), jj.ravel()], 1).astype(np.float64)  # [HW, 2]
    lab = fg.ravel()
    out = np.ones(H * W, dtype=np.float32)
    if n <= 0:
        return out.reshape(H, W)
    d2 = ((pts[:, None, :] - pts[None, :, :]) ** 2).sum(-1)  # [HW, HW]
    other = lab[:, None] != lab[None, :]
    near = (np.where(other, d2, np.inf) <= n * n).any(1)
    out[near] = 0.0
    return out.reshape(H, W)
