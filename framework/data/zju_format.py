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
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
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


ROTATION_TOL = 1e-3  # |R R^T - I| and |det R - 1| a calibration rotation may be off by (float32 exports, rounding)
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


def read_mask_file(path: Path) -> np.ndarray:
    """uint8 [H, W] in {0, 1}: foreground wherever the stored value (first channel) is non-zero."""
    import cv2

    check_complete(path, "mask file")
    m = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if m is None:
        raise ZjuFormatError(f"mask file {path} exists but cannot be decoded as an image; export it again")
    if m.ndim == 3:
        m = m[..., 2] if m.shape[2] >= 3 else m[..., 0]  # cv2 gives BGR(A): the first stored channel is R
    return (m != 0).astype(np.uint8)


# ----------------------------------------------------------------------------------------------------------- writer
class ZjuWriter:
    """Writes a sequence in the public layout.

    Usage:
        w = ZjuWriter(root, zju_camera_names(21))
        w.write_cameras(K, D, R, T_m)          # K in splatrig's pixel convention (centre of pixel (i, j) at j+.5, i+.5)
        for f in range(F): w.write_frame(f, images, masks, params, vertices)
        w.finish()                              # writes annots.npy; a sequence without it is incomplete

    Frames may be written by several writer instances (processes) into the same root; `finish(num_frames)` rebuilds
    the `ims` list from the deterministic names, so any one process can finish. Until `finish`, there is no
    annots.npy, so a half-written sequence is never mistaken for a complete one. Every file is written atomically and
    a frame is marked done (`.frames_done/<frame>`) only after all its files, so an interrupted writer can be resumed
    with `frame_done` telling which frames are complete.
    """

    def __init__(
        self,
        root: str | os.PathLike,
        camera_names: Sequence[str],
        *,
        style: str = "zju",
        image_ext: str = ".jpg",
        jpeg_quality: int = 95,
        mask_dir: str = "mask",
        sequence: str = "313",
        mask_value: int = 255,
    ) -> None:
        if style not in ("zju", "core313"):
            raise ValueError(f"style must be 'zju' or 'core313', got '{style}'")
        if mask_dir not in MASK_DIRS:
            raise ValueError(f"mask_dir must be one of {MASK_DIRS}, got '{mask_dir}'")
        self.root = Path(root)
        self.camera_names = list(camera_names)
        self.style = style
        self.image_ext = image_ext
        self.jpeg_quality = jpeg_quality
        self.mask_dir = mask_dir
        self.sequence = sequence
        self.mask_value = int(mask_value)
        self._cams: dict | None = None
        self._written: set[int] = set()
        self.root.mkdir(parents=True, exist_ok=True)

    @property
    def num_cameras(self) -> int:
        return len(self.camera_names)

    def image_path(self, frame: int, view: int) -> str:
        return image_relpath(self.camera_names[view], frame, self.style, self.image_ext, self.sequence)

    def file_number(self, frame: int) -> int:
        """Number in params/{n}.npy for 0-based `frame` (1-based for the 313/315 style)."""
        return frame + 1 if self.style == "core313" else frame

    def write_cameras(
        self,
        K: np.ndarray,  # [C, 3, 3]
        D: np.ndarray | None,  # [C, 5] (or [C, 5, 1]); None = no distortion
        R: np.ndarray,  # [C, 3, 3] world-to-camera rotation
        T_m: np.ndarray,  # [C, 3] world-to-camera translation in METRES
        *,
        k_convention: str = "splatrig",
    ) -> None:
        """Store the rig. `k_convention`: "splatrig" (pixel centres at j + 0.5, as framework.types and gsplat) is
        converted to OpenCV's convention on disk (cx, cy minus 0.5); "opencv" stores K as given."""
        C = self.num_cameras
        K = np.asarray(K, dtype=np.float64).reshape(C, 3, 3).copy()
        R = np.asarray(R, dtype=np.float64).reshape(C, 3, 3)
        T = np.asarray(T_m, dtype=np.float64).reshape(C, 3, 1) * 1000.0
        D = np.zeros((C, 5, 1)) if D is None else np.asarray(D, dtype=np.float64).reshape(C, -1, 1)
        if k_convention == "splatrig":
            K[:, 0, 2] -= 0.5
            K[:, 1, 2] -= 0.5
        elif k_convention != "opencv":
            raise ValueError(f"k_convention must be 'splatrig' or 'opencv', got '{k_convention}'")
        for name, arr in (("K", K), ("D", D), ("R", R), ("T", T)):
            if not np.isfinite(arr).all():
                raise ValueError(f"camera {name} has non-finite values")
        self._cams = {
            "K": [k for k in K],
            "D": [d for d in D],
            "R": [r for r in R],
            "T": [t for t in T],
        }
        save_pickled_dict(self.root / ".cams_partial.npy", self._cams)  # lets another process finish()

    def write_frame(
        self,
        frame: int,
        images: np.ndarray,  # [C, H, W, 3] uint8 RGB
        masks: np.ndarray,  # [C, H, W] uint8 / bool, foreground non-zero
        params: dict | None = None,  # poses [1, J*3] or [J, 3], Rh [1, 3], Th [1, 3], shapes [1, S], body: str
        vertices: np.ndarray | None = None,  # [V, 3] posed world vertices, metres
    ) -> None:
        C = self.num_cameras
        images = np.asarray(images)
        masks = np.asarray(masks)
        if images.ndim != 4 or images.shape[0] != C or images.shape[-1] != 3:
            raise ValueError(f"frame {frame}: images must be [C={C}, H, W, 3] uint8, got {images.shape}")
        if masks.shape != images.shape[:3]:
            raise ValueError(f"frame {frame}: masks must be {images.shape[:3]}, got {masks.shape}")
        if images.dtype != np.uint8:
            raise ValueError(f"frame {frame}: images must be uint8, got {images.dtype}")
        for v in range(C):
            rel = self.image_path(frame, v)
            write_image(self.root / rel, images[v], self.jpeg_quality)
            m = (masks[v] != 0).astype(np.uint8) * np.uint8(self.mask_value)
            write_image(self.root / self.mask_dir / mask_relpath(rel), m)
        n = self.file_number(frame)
        if params is not None:
            save_pickled_dict(self.root / "params" / f"{n}.npy", normalize_params(params, f"frame {frame}"))
        if vertices is not None:
            verts = np.asarray(vertices, dtype=np.float32)
            if verts.ndim != 2 or verts.shape[1] != 3:
                raise ValueError(f"frame {frame}: vertices must be [V, 3], got {verts.shape}")
            with atomic_path(self.root / "vertices" / f"{n}.npy") as tmp:
                np.save(tmp, verts)
        with atomic_path(self.root / self.DONE / str(frame)) as tmp:
            tmp.touch()
        self._written.add(frame)

    DONE = ".frames_done"

    def frame_done(self, frame: int) -> bool:
        """Every file of `frame` was written (by this or an earlier, interrupted writer)."""
        return (self.root / self.DONE / str(frame)).is_file()

    def finish(self, num_frames: int | None = None) -> Path:
        """Write annots.npy for frames 0..num_frames-1 (default: 0..max written); checks every image exists."""
        cams = self._cams
        partial = self.root / ".cams_partial.npy"
        if cams is None and partial.exists():
            cams = load_pickled_dict(partial)
        if cams is None:
            raise RuntimeError("ZjuWriter.finish: call write_cameras first")
        if num_frames is None:
            if not self._written:
                raise RuntimeError("ZjuWriter.finish: no frame written; pass num_frames when other writers wrote them")
            num_frames = max(self._written) + 1
        ims = []
        missing = []
        for f in range(num_frames):
            row = [self.image_path(f, v) for v in range(self.num_cameras)]
            missing += [r for r in row if not (self.root / r).exists()]
            ims.append({"ims": row})
        if missing:
            raise FileNotFoundError(
                f"ZjuWriter.finish: {len(missing)} image(s) of frames 0..{num_frames - 1} were never written under "
                f"{self.root}, e.g. {missing[0]}"
            )
        out = self.root / ANNOTS
        save_pickled_dict(out, {"cams": cams, "ims": ims})
        if partial.exists():
            partial.unlink()
        shutil.rmtree(self.root / self.DONE, ignore_errors=True)
        return out


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


# ----------------------------------------------------------------------------------------------------------- reader
@dataclass
class ZjuCameras:
    """The rig exactly as stored (float64, OpenCV pixel convention, T in mm), plus converted views of it."""

    K: np.ndarray  # [C, 3, 3] OpenCV convention (pixel centres at integers)
    D: np.ndarray  # [C, 5] distortion (k1, k2, p1, p2, k3), zero-padded
    R: np.ndarray  # [C, 3, 3]
    T_mm: np.ndarray  # [C, 3]

    @property
    def num(self) -> int:
        return int(self.K.shape[0])

    @property
    def T_m(self) -> np.ndarray:
        return self.T_mm / 1000.0  # [C, 3]

    def world_to_cam(self) -> np.ndarray:
        out = np.tile(np.eye(4), (self.num, 1, 1))  # [C, 4, 4]
        out[:, :3, :3] = self.R
        out[:, :3, 3] = self.T_m
        return out

    def K_splatrig(self) -> np.ndarray:
        """K with pixel centres at (j + 0.5, i + 0.5), the convention of framework.types / the rasterizers."""
        K = self.K.copy()
        K[:, 0, 2] += 0.5
        K[:, 1, 2] += 0.5
        return K


class ZjuSequence:
    """Lazy reader of one sequence: parses annots.npy; images, masks, params and vertices are read on demand."""

    def __init__(self, root: str | os.PathLike) -> None:
        self.root = Path(root)
        path = self.root / ANNOTS
        if not path.exists():
            hint = ""
            if (self.root / ".cams_partial.npy").exists():
                hint = " A writer started here but never called finish(); re-run the generator."
            raise ZjuMissingFileError(
                f"{path} is missing: expected annots.npy (dict with 'cams' K/D/R/T and per-frame 'ims') at the root "
                f"of a ZJU-MoCap-layout sequence; check `root` (found {self._listing()}).{hint}"
            )
        annots = load_pickled_dict(path)
        for key in ("cams", "ims"):
            if key not in annots:
                raise ZjuFormatError(f"{path}: expected keys 'cams' and 'ims', found {sorted(annots)}")
        self.cameras = self._parse_cams(annots["cams"], path)
        self.ims = self._parse_ims(annots["ims"], path)
        self.camera_dirs = [os.path.dirname(p) for p in self.ims[0]]
        self.file_numbers = [frame_number_from_path(row[0]) for row in self.ims]
        self.params_dir = next((d for d in PARAMS_DIRS if (self.root / d).is_dir()), None)
        self.vertices_dir = next((d for d in VERTICES_DIRS if (self.root / d).is_dir()), None)

    def _listing(self) -> str:
        if not self.root.exists():
            return "the directory does not exist"
        names = sorted(p.name for p in self.root.iterdir())[:8]
        return ", ".join(names) if names else "an empty directory"

    def _parse_cams(self, cams: dict, path: Path) -> ZjuCameras:
        for key in ("K", "R", "T"):
            if key not in cams:
                raise ZjuFormatError(f"{path}: cams must have K, D, R, T; '{key}' is missing (found {sorted(cams)})")
        C = len(cams["K"])
        for key in ("R", "T") + (("D",) if "D" in cams else ()):
            if len(cams[key]) != C:
                raise ZjuFormatError(
                    f"{path}: cams['{key}'] lists {len(cams[key])} cameras but cams['K'] lists {C}; every camera "
                    f"needs K, D, R and T"
                )
        K = np.asarray(cams["K"], dtype=np.float64).reshape(C, 3, 3)
        R = np.asarray(cams["R"], dtype=np.float64).reshape(C, 3, 3)
        T = np.asarray(cams["T"], dtype=np.float64).reshape(C, 3)
        D = np.zeros((C, 5))
        if "D" in cams:
            for c, d in enumerate(cams["D"]):
                d = np.asarray(d, dtype=np.float64).ravel()
                D[c, : min(5, d.size)] = d[:5]
        for name, arr in (("K", K), ("D", D), ("R", R), ("T", T)):
            bad = np.where(~np.isfinite(arr).reshape(C, -1).all(1))[0]
            if bad.size:
                raise ZjuFormatError(f"{path}: cams['{name}'] of camera {int(bad[0])} has non-finite values")
        for c in range(C):
            off = float(np.abs(R[c] @ R[c].T - np.eye(3)).max())
            det = float(np.linalg.det(R[c]))
            if off > ROTATION_TOL or abs(det - 1.0) > ROTATION_TOL:
                raise ZjuFormatError(
                    f"{path}: cams['R'] of camera {c} is not a rotation (|R R^T - I| = {off:.3g}, det = {det:.3g}); "
                    f"expected an orthonormal world-to-camera rotation with det +1. Export the calibration again "
                    f"(a scaled or mirrored R is not a camera pose)."
                )
            fx, fy = float(K[c, 0, 0]), float(K[c, 1, 1])
            if fx <= 0 or fy <= 0 or np.abs(K[c, 2] - [0.0, 0.0, 1.0]).max() > 1e-6:
                raise ZjuFormatError(
                    f"{path}: cams['K'] of camera {c} has fx = {fx:g}, fy = {fy:g}, last row {K[c, 2].tolist()}; "
                    f"expected positive focal lengths in pixels, K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]."
                )
        return ZjuCameras(K=K, D=D, R=R, T_mm=T)

    def _parse_ims(self, ims: list, path: Path) -> list[list[str]]:
        if len(ims) == 0:
            raise ZjuFormatError(f"{path}: 'ims' lists no frames")
        C = self.cameras.num
        rows: list[list[str]] = []
        for f, entry in enumerate(ims):
            row = entry["ims"] if isinstance(entry, dict) else entry
            row = [str(p) for p in np.asarray(row).ravel()]
            if len(row) != C:
                raise ZjuFormatError(
                    f"{path}: frame {f} of 'ims' lists {len(row)} images but 'cams' has {C} cameras; the image "
                    f"folders and the calibration must describe the same rig"
                )
            rows.append(row)
        dirs = sorted({os.path.dirname(p) for row in rows[:1] for p in row})
        if len(dirs) != C:
            raise ZjuFormatError(
                f"{path}: frame 0 of 'ims' uses {len(dirs)} image folder(s) for {C} cameras ({dirs[:4]}...); "
                f"expected one folder per camera"
            )
        missing = [d for d in dirs if not (self.root / d).is_dir()]
        if missing:
            present = sorted(p.name for p in self.root.iterdir() if p.is_dir())
            raise ZjuFormatError(
                f"{path}: 'cams' has {C} cameras but {len(missing)} of their image folders are missing under "
                f"{self.root} (e.g. '{missing[0]}'); found folders {present}"
            )
        return rows

    # -------------------------------------------------------------------------------------------------- access
    @property
    def num_frames(self) -> int:
        return len(self.ims)

    @property
    def num_views(self) -> int:
        return self.cameras.num

    @property
    def one_based(self) -> bool:
        """True for 313/315-style sequences whose file numbers count from 1."""
        return self.file_numbers[0] == 1

    def image_path(self, frame: int, view: int) -> Path:
        return self.root / self.ims[frame][view]

    def image(self, frame: int, view: int) -> np.ndarray:
        """uint8 [H, W, 3] RGB, as stored (distorted)."""
        path = self.image_path(frame, view)
        if not path.exists():
            raise ZjuMissingFileError(
                f"image file {path} of frame {frame}, view {view} is missing: annots.npy lists "
                f"'{self.ims[frame][view]}' but no such file exists under {self.root} (expected a {path.suffix} image)"
            )
        return read_image(path)

    def check_files(self, frames: list[int], views: list[int], mask_dir: str = "auto") -> tuple[int, int]:
        """Open every image and mask of (frames x views) far enough to know it is there, complete, and of one size
        with its mask and the other images (headers only: ~1 ms a pair); returns (width, height). Errors name the
        file, the frame and the view."""
        from PIL import Image, UnidentifiedImageError

        def size(path: Path, what: str, frame: int, view: int) -> tuple[int, int]:
            try:
                with Image.open(path) as im:
                    wh = im.size
            except (UnidentifiedImageError, OSError) as exc:
                raise ZjuFormatError(f"{what} {path} (frame {frame}, view {view}) cannot be read as an image "
                                     f"({type(exc).__name__}); export it again") from None  # fmt: skip
            check_complete(path, what)
            return wh

        expected: tuple[int, int] | None = None
        for f in frames:
            for v in views:
                image = self.image_path(f, v)
                if not image.exists():
                    self.image(f, v)  # raises the missing-image message
                wh = size(image, "image file", f, v)
                if expected is None:
                    expected, first = wh, image
                elif wh != expected:
                    raise ZjuFormatError(
                        f"{image} (frame {f}, view {v}): image is {wh[0]}x{wh[1]} but {first.name} of frame "
                        f"{frames[0]}, view {views[0]} is {expected[0]}x{expected[1]}; every image of a sequence must "
                        f"have the same size"
                    )
                mask = self.mask_path(f, v, mask_dir)
                mwh = size(mask, "mask file", f, v)
                if mwh != wh:
                    raise ZjuFormatError(
                        f"{mask} (frame {f}, view {v}): mask is {mwh[0]}x{mwh[1]} (WxH) but its image {image.name} is "
                        f"{wh[0]}x{wh[1]}; masks must match their images pixel for pixel"
                    )
        assert expected is not None
        return expected

    def available_mask_dirs(self) -> list[str]:
        return [d for d in MASK_DIRS if (self.root / d).is_dir()]

    def mask_path(self, frame: int, view: int, mask_dir: str = "auto") -> Path:
        """Animatable NeRF's search order for "auto": mask_cihp/, mask/, then images -> mask in the image path."""
        rel = self.ims[frame][view]
        dirs = MASK_DIRS if mask_dir == "auto" else (mask_dir,)
        candidates = [self.root / d / mask_relpath(rel) for d in dirs]
        if mask_dir == "auto" and "images" in rel:
            swapped = rel.replace("images", "mask")
            candidates += [self.root / mask_relpath(swapped), self.root / (os.path.splitext(swapped)[0] + ".jpg")]
        for c in candidates:
            if c.exists():
                return c
        raise ZjuMissingFileError(
            f"mask of frame {frame}, view {view} is missing: looked for {', '.join(str(c) for c in candidates)}"
        )

    def mask(self, frame: int, view: int, mask_dir: str = "auto") -> np.ndarray:
        """uint8 [H, W] in {0, 1}."""
        return read_mask_file(self.mask_path(frame, view, mask_dir))

    def _numbered(self, dirname: str | None, kind: str, frame: int) -> Path:
        n = self.file_numbers[frame]
        if dirname is None:
            raise ZjuMissingFileError(
                f"{kind} of frame {frame}: no {' or '.join(PARAMS_DIRS if kind == 'params' else VERTICES_DIRS)} "
                f"folder under {self.root}"
            )
        for name in (f"{n}.npy", f"{n:06d}.npy"):
            p = self.root / dirname / name
            if p.exists():
                return p
        raise ZjuMissingFileError(
            f"{kind} of frame {frame} is missing: expected {self.root / dirname / f'{n}.npy'} (file number {n} from "
            f"image '{self.ims[frame][0]}')"
        )

    def params_path(self, frame: int) -> Path:
        return self._numbered(self.params_dir, "params", frame)

    def params(self, frame: int) -> dict:
        """The stored dict (poses [1, J*3], Rh, Th, shapes, optional body)."""
        path = self.params_path(frame)
        d = load_pickled_dict(path)
        for key in ("poses", "Rh", "Th"):
            if key not in d:
                raise ZjuFormatError(f"{path}: expected keys poses, Rh, Th (and shapes), found {sorted(d)}")
        return d

    def vertices_path(self, frame: int) -> Path:
        return self._numbered(self.vertices_dir, "vertices", frame)

    def vertices(self, frame: int) -> np.ndarray:
        """[V, 3] float32 posed world vertices."""
        path = self.vertices_path(frame)
        v = np.load(path).astype(np.float32)
        if v.ndim != 2 or v.shape[1] != 3:
            raise ZjuFormatError(f"{path}: expected vertices [V, 3], found shape {v.shape}")
        return v


# ----------------------------------------------------------------------------------------------------------- checks
def check_body_compatible(dataset: object, body: object) -> None:
    """Stop before training when the stored poses cannot drive `body` (different joint count).

    `dataset` has `poses()` [F, J, 3] (any MultiViewDataset) and optionally `root`/`body_name`; `body` has
    `num_joints` (a BodyModel). The message names the params file, the body and the fix.
    """
    poses = dataset.poses() if hasattr(dataset, "poses") else None
    if poses is None:
        return
    J_data = int(poses.shape[1])
    J_body = int(body.num_joints)
    if J_data == J_body:
        return
    where = getattr(dataset, "root", "the dataset")
    seq = getattr(dataset, "seq", None)
    if seq is not None and getattr(dataset, "frame_ids", None):
        try:
            where = seq.params_path(dataset.frame_ids[0])
        except FileNotFoundError:
            pass
    body_name = getattr(body, "registry_name", "") or type(body).__name__
    stored = getattr(dataset, "body_name", None)
    raise ZjuFormatError(
        f"{where}: stored poses have {J_data} joints ({J_data * 3} values per frame) but body model '{body_name}' has "
        f"{J_body} joints. The poses were made for body '{stored}'; select that body (body={stored}) or convert the "
        f"poses."
    )
