"""Save a picture of one frame of a ZJU-MoCap-layout sequence from four views: the image as the loader delivers it
(undistorted, downscaled), the mask tinted over it with its outline, and the stored posed vertices projected with the
loader's cameras as dots (green inside the mask, red outside), so calibration, masks and poses can be checked by
eye. Also prints, per view, the share of projected vertices that land inside the mask (>= 0.99 for a consistent
sequence).

    python tools/preview_sequence.py --root /data/zju_mocap/CoreView_377 --frame 0 --views 0 6 12 18 --out prev.png
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from framework.data.calibration_check import project
from framework.data.overlay import render_tile


def preview(
    root: str,
    frame: int,
    views: list[int] | None,
    out: str,
    downscale: float = 1.0,
    mask_dir: str = "auto",
    crop: bool = True,
) -> list[float]:
    """Writes the PNG; returns the in-mask share of projected vertices per view."""
    import cv2

    from framework.data.zju.dataset import ZjuMocapDataset

    probe = ZjuMocapDataset(
        root, protocol=None, train_frames=[frame], downscale=downscale, mask_dir=mask_dir, cache_mb=0
    )
    C = probe.cameras.num
    if views is None:
        views = sorted({round(k * C / 4) % C for k in range(4)})
    ds = ZjuMocapDataset(
        root,
        protocol=None,
        train_frames=[frame],
        train_views=views,
        downscale=downscale,
        mask_dir=mask_dir,
        mask_background=False,
        cache_mb=0,
    )
    verts = ds.vertices(frame).double() if ds.seq.vertices_dir is not None else None
    tiles, shares = [], []
    for k in range(len(ds)):
        b = ds[k]
        v = int(b.view[0])
        uv = None
        if verts is not None:
            uv, z = project(verts.numpy(), b.cameras.K[0].double().numpy(), b.cameras.world_to_cam[0].double().numpy())
            uv = uv[z > 1e-6]
        label = f"frame {frame} view {v} ({ds.seq.camera_dirs[v]})"
        tile, share = render_tile(b.image[0].numpy(), b.mask[0].numpy(), uv, label, crop)
        tiles.append(tile)
        shares.append(share)
    while len(tiles) % 2 and len(tiles) > 1:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.concatenate(tiles[i : i + 2], 1) for i in range(0, len(tiles), 2)] if len(tiles) > 1 else tiles
    grid = np.concatenate(rows, 0)
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), grid[..., ::-1]):
        raise OSError(f"could not write {out}")
    return shares


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", required=True, help="sequence folder holding annots.npy")
    ap.add_argument("--frame", type=int, default=0, help="frame index (position in annots 'ims', 0-based)")
    ap.add_argument("--views", type=int, nargs="*", default=None, help="view indices (default: four spread views)")
    ap.add_argument("--out", default="preview.png", help="output PNG path")
    ap.add_argument("--downscale", type=float, default=1.0, help="image size divisor, as the loader's `downscale`")
    ap.add_argument("--mask-dir", default="auto", choices=["auto", "mask", "mask_cihp"])
    ap.add_argument("--no-crop", action="store_true", help="show whole images instead of crops around the mask")
    args = ap.parse_args(argv)
    shares = preview(args.root, args.frame, args.views, args.out, args.downscale, args.mask_dir, not args.no_crop)
    print(f"wrote {args.out}")
    for s in shares:
        print(f"  projected vertices inside the mask: {s:.2%}" if s == s else "  (no vertices/ folder)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
