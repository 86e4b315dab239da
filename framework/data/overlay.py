"""Pictures for checking a sequence by eye: an image with its mask tinted over it, the mask's outline, projected
vertices as dots (green inside the mask, red outside) and optionally the outline of the projected mesh silhouette.
Used by `python -m framework.data.check` and `tools/preview_sequence.py`."""

from __future__ import annotations

import numpy as np

from framework.atomic import atomic_path

MASK_TINT = (40, 200, 255)
MASK_OUTLINE = (255, 255, 0)
SILHOUETTE_OUTLINE = (255, 60, 200)


def render_tile(
    image: np.ndarray,
    mask: np.ndarray,
    uv: np.ndarray | None,
    label: str,
    crop: bool = True,
    side: int = 384,
    silhouette: np.ndarray | None = None,
) -> tuple[np.ndarray, float]:
    """image float [H, W, 3] in [0, 1], mask [H, W] in [0, 1], uv [N, 2] pixel coords (centres at +0.5),
    silhouette bool [H, W] or None -> a side x side uint8 RGB tile (cropped around the mask unless `crop` is false)
    and the share of dots inside the mask."""
    import cv2

    fg = mask >= 0.5
    H, W = fg.shape
    inside = float("nan")
    if uv is not None and len(uv):
        j, i = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        ok = (j >= 0) & (j < W) & (i >= 0) & (i < H)
        inside = float(fg[i[ok], j[ok]].sum()) / len(uv)
    # crop window (pixel box) around the silhouette, square, 25% margin
    i0, i1, j0, j1 = 0, H, 0, W
    if crop and fg.any():
        ii, jj = np.nonzero(fg)
        half = int(0.625 * max(np.ptp(ii), np.ptp(jj))) + 8
        ci, cj = (ii.min() + ii.max()) // 2, (jj.min() + jj.max()) // 2
        i0, i1, j0, j1 = max(0, ci - half), min(H, ci + half), max(0, cj - half), min(W, cj + half)
    f = side / max(i1 - i0, j1 - j0)
    size = (max(1, round((j1 - j0) * f)), max(1, round((i1 - i0) * f)))
    interp = cv2.INTER_AREA if f < 1 else cv2.INTER_NEAREST
    tile = cv2.resize((image[i0:i1, j0:j1] * 255).astype(np.uint8), size, interpolation=interp)
    fgt = cv2.resize(fg[i0:i1, j0:j1].astype(np.uint8), size, interpolation=cv2.INTER_NEAREST).astype(bool)
    tint = np.array(MASK_TINT, np.float32)
    tile[fgt] = (0.55 * tile[fgt] + 0.45 * tint).astype(np.uint8)
    contours, _ = cv2.findContours(fgt.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(tile, contours, -1, MASK_OUTLINE, 1)
    if silhouette is not None:
        sil = cv2.resize(silhouette[i0:i1, j0:j1].astype(np.uint8), size, interpolation=cv2.INTER_NEAREST)
        contours, _ = cv2.findContours(sil, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(tile, contours, -1, SILHOUETTE_OUTLINE, 1)
    if uv is not None and len(uv):
        step = max(1, len(uv) // 800)
        for (u, v), good in zip(uv[::step], ok[::step], strict=True):
            colour = (60, 255, 60) if good and fg[int(np.floor(v)), int(np.floor(u))] else (255, 40, 40)
            x, y = (u - j0) * f, (v - i0) * f
            if -1e4 < x < 1e4 and -1e4 < y < 1e4:
                cv2.circle(tile, (int(x), int(y)), 1, colour, -1)
    canvas = np.zeros((side, side, 3), np.uint8)
    canvas[: tile.shape[0], : tile.shape[1]] = tile
    text = f"{label}  dots in mask {inside:.1%}" if uv is not None else label
    for colour, thick in (((0, 0, 0), 3), ((255, 255, 255), 1)):
        cv2.putText(canvas, text, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.42, colour, thick, cv2.LINE_AA)
    return canvas, inside


def write_png(path, rgb: np.ndarray) -> None:
    """Atomic PNG write of a uint8 RGB picture (framework.atomic)."""
    import cv2

    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(rgb[..., ::-1])):
            raise OSError(f"could not write {path}")
