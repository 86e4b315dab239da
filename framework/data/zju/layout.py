"""The ZJU-MoCap / Neural Body / Animatable NeRF on-disk layout: a writer and a lazy reader.

Real users bring ZJU-MoCap, H36M or CMU Panoptic sequences prepared in this layout, and our synthetic studio writes the
very same layout, so one reader serves both. The layout, as the public loaders read it (zju3dv/neuralbody
`lib/datasets/light_stage/can_smpl.py`, zju3dv/animatable_nerf `lib/datasets/tpose_dataset.py` and
`tpose_pdf_dataset.py`, the EasyMocap-style `get_annots.py` scripts that build `annots.npy`):

    <root>/
      annots.npy             np.save of a dict (read with np.load(..., allow_pickle=True).item()):
                               cams: {K: [C x (3,3)], D: [C x (5,1)], R: [C x (3,3)], T: [C x (3,1)]}
                                 world-to-camera, OpenCV (x right, y down, z forward): x_cam = R x_world + T / 1000;
                                 T is in MILLIMETRES (the scripts store EasyMocap's metres * 1000);
                                 D are OpenCV distortion coefficients (k1, k2, p1, p2, k3), D = dist.T;
                                 K is in OpenCV's pixel convention: pixel (i, j) has its centre at (j, i).
                               ims: [F x {"ims": [C relative image paths]}]  (real files also carry kpts2d; ignored)
      Camera_B1/000000.jpg   images, one folder per camera, frame number = file stem (0-based);
      ...                    313/315 instead: "Camera (1)/CoreView_313_Camera_(1)_0001_2019-08-23_16-08-50.592.jpg",
                             the 4-digit field (basename.split('_')[4]) counting frames from 1;
                             EasyMocap/H36M/CMU preparations use other folder names (e.g. images/<cam>/000000.jpg),
                             which is why the reader takes every path from annots["ims"] and never assumes names.
      mask/<image path>.png  foreground masks mirroring the image paths with the extension replaced by .png;
      mask_cihp/<...>.png    CIHP human-parsing masks (part labels); both read as foreground = value != 0 (first
                             channel if stored as RGB). Animatable NeRF looks for mask_cihp, then mask, then the
                             image path with "images" replaced by "mask" (.png, then .jpg) - we do the same.
      params/{i}.npy         per frame (i = the frame number in the image name: 0-based, or 1-based for 313/315;
                             Animatable NeRF also accepts {i:06d}.npy): np.save of a dict with
                               poses [1, J*3] axis-angle (SMPL: J = 24, the first triple is the global orient),
                               Rh [1, 3] axis-angle, Th [1, 3] metres, shapes [1, S];
                             we add "body": the registry name of the body model the poses belong to.
                             EasyMocap root convention: world = R(Rh) @ M(poses, shapes) + Th, about the origin.
      vertices/{i}.npy       posed world vertices [V, 3] float32 (metres), same numbering as params.
    (Animatable NeRF's own preparations name these new_params/ and new_vertices/; the reader looks for both.)

Images are distorted as captured: loaders undistort them with cv2.undistort(img, K, D) and keep K unchanged.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from framework.atomic import atomic_path
from framework.errors import SplatrigError

ANNOTS = "annots.npy"
MASK_DIRS = ("mask_cihp", "mask")
PARAMS_DIRS = ("params", "new_params")
VERTICES_DIRS = ("vertices", "new_vertices")
_CORE313 = re.compile(r"_\((\d+)\)_(\d+)_")  # CoreView_313_Camera_(1)_0001_2019-... -> camera 1, frame 1


class ZjuFormatError(SplatrigError, ValueError):
    """A sequence on disk does not follow the layout; the message names the file, what was expected and found."""


class ZjuMissingFileError(ZjuFormatError, FileNotFoundError):
    """A file the layout needs is missing (still a FileNotFoundError for code that tolerates optional files)."""


IMAGE_END_MARKERS = {".jpg": b"\xff\xd9", ".jpeg": b"\xff\xd9", ".png": b"IEND\xaeB`\x82"}


def check_complete(path: Path, what: str = "image file") -> None:
    """Raise ZjuFormatError when a JPEG or PNG file lacks its end marker: a copy or an export cut short. (OpenCV
    decodes a truncated JPEG without an error, grey below the cut.)"""
    marker = IMAGE_END_MARKERS.get(path.suffix.lower())
    if marker is None:
        return
    with open(path, "rb") as f:
        f.seek(0, os.SEEK_END)
        f.seek(max(0, f.tell() - 64))
        tail = f.read()
    if marker not in tail:
        end = "end-of-image marker FF D9" if path.suffix.lower() in (".jpg", ".jpeg") else "IEND chunk"
        raise ZjuFormatError(
            f"{what} {path} is truncated: it does not end with the {path.suffix.lstrip('.').upper()} {end}; copy or "
            f"export it again."
        )


# ----------------------------------------------------------------------------------------------------------- naming
def zju_camera_names(num_cameras: int, style: str = "zju") -> list[str]:
    """Folder names of the public data: "Camera_B1".. (most ZJU sequences) or "Camera (1)".. (313/315)."""
    if style == "zju":
        return [f"Camera_B{c + 1}" for c in range(num_cameras)]
    if style == "core313":
        return [f"Camera ({c + 1})" for c in range(num_cameras)]
    raise ValueError(f"unknown naming style '{style}'; expected 'zju' or 'core313'")


def image_relpath(camera_name: str, frame: int, style: str = "zju", ext: str = ".jpg", sequence: str = "313") -> str:
    """Relative image path of 0-based `frame` in camera folder `camera_name`, in the public naming of `style`."""
    if style == "zju":
        return f"{camera_name}/{frame:06d}{ext}"
    if style == "core313":
        m = re.search(r"\((\d+)\)", camera_name)
        cam = m.group(1) if m else camera_name
        # a plausible capture timestamp: 16-08-50.592 plus 1/30 s per frame, as in the public names
        t = 50.592 + frame / 30.0
        stamp = f"2019-08-23_16-{8 + int(t // 60):02d}-{t % 60:06.3f}"
        return f"{camera_name}/CoreView_{sequence}_Camera_({cam})_{frame + 1:04d}_{stamp}{ext}"
    raise ValueError(f"unknown naming style '{style}'; expected 'zju' or 'core313'")


def frame_number_from_path(path: str) -> int:
    """The number params/ and vertices/ files are named by, parsed from an image path (1-based for 313/315)."""
    base = os.path.basename(path)
    stem = os.path.splitext(base)[0]
    if stem.isdigit():
        return int(stem)
    m = _CORE313.search(base)
    if m:
        return int(m.group(2))
    digits = re.findall(r"\d+", stem)
    if not digits:
        raise ZjuFormatError(f"cannot parse a frame number from image name '{path}' (expected e.g. 000000.jpg)")
    return int(digits[-1])


def mask_relpath(image_path: str) -> str:
    """Masks mirror image paths with a .png extension."""
    return os.path.splitext(image_path)[0] + ".png"


# ----------------------------------------------------------------------------------------------------------- io
def save_pickled_dict(path: Path, data: dict) -> None:
    """np.save of a dict, as the public files are (a pickled 0-d object array); atomic."""
    with atomic_path(path) as tmp:
        np.save(tmp, np.array(data, dtype=object), allow_pickle=True)


def load_pickled_dict(path: Path) -> dict:
    try:
        obj = np.load(path, allow_pickle=True)
    except FileNotFoundError:
        raise
    except Exception as exc:
        raise ZjuFormatError(f"{path}: cannot be read as a numpy file ({type(exc).__name__}: {exc})") from exc
    if isinstance(obj, np.ndarray) and obj.dtype == object and obj.shape == ():
        obj = obj.item()
    if not isinstance(obj, dict):
        raise ZjuFormatError(f"{path}: expected a pickled dict (np.save of a dict), found {type(obj).__name__}")
    return obj


def write_image(path: Path, rgb: np.ndarray, jpeg_quality: int = 95) -> None:
    """RGB uint8 [H, W, 3] (or a single-channel mask [H, W]) to a JPEG/PNG file, atomically."""
    import cv2

    params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if path.suffix.lower() in (".jpg", ".jpeg") else []
    pixels = np.ascontiguousarray(rgb[..., ::-1] if rgb.ndim == 3 else rgb)
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), pixels, params):
            raise OSError(f"could not write image {path}")


def read_image(path: Path) -> np.ndarray:
    """uint8 [H, W, 3] RGB."""
    import cv2

    if not path.exists():
        raise ZjuMissingFileError(f"image file {path} is missing (listed in annots.npy 'ims')")
    check_complete(path)
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise ZjuFormatError(f"image file {path} exists but cannot be decoded as an image; export it again")
    return img[..., ::-1].copy()


def read_mask_file(path: Path, any_channel: bool = False) -> np.ndarray:
    """uint8 [H, W] in {0, 1}: foreground wherever the stored value (first channel) is non-zero; with `any_channel`,
    wherever any colour channel is (part-label masks such as SCHP's palette PNGs colour some parts with R = 0)."""
    import cv2

    check_complete(path, "mask file")
    m = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if m is None:
        raise ZjuFormatError(f"mask file {path} exists but cannot be decoded as an image; export it again")
    if m.ndim == 3:
        if any_channel:
            return (m[..., :3] != 0).any(-1).astype(np.uint8)
        m = m[..., 2] if m.shape[2] >= 3 else m[..., 0]  # cv2 gives BGR(A): the first stored channel is R
    return (m != 0).astype(np.uint8)


def normalize_params(params: dict, where: str) -> dict:
    """Shapes as the public files store them: poses [1, J*3], Rh [1, 3], Th [1, 3], shapes [1, S] (float32)."""
    out = dict(params)
    for key in ("poses", "Rh", "Th", "shapes"):
        if key not in params:
            if key == "shapes":
                out[key] = np.zeros((1, 10), dtype=np.float32)
                continue
            raise ValueError(f"{where}: params must have '{key}'")
        out[key] = np.asarray(params[key], dtype=np.float32).reshape(1, -1)
    if out["Rh"].shape[1] != 3 or out["Th"].shape[1] != 3:
        raise ValueError(f"{where}: Rh and Th must have 3 values, got {out['Rh'].shape}, {out['Th'].shape}")
    if out["poses"].shape[1] % 3:
        raise ValueError(f"{where}: poses must hold J*3 values, got {out['poses'].shape[1]}")
    return out
