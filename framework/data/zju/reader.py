"""Reads a sequence in the ZJU-MoCap layout lazily (`framework.data.zju.layout` documents it): cameras as stored,
image/mask/params/vertices paths by frame and view, and the body-compatibility check."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from framework.data.zju.layout import (
    ANNOTS,
    MASK_DIRS,
    PARAMS_DIRS,
    VERTICES_DIRS,
    ZjuFormatError,
    ZjuMissingFileError,
    frame_number_from_path,
    load_pickled_dict,
    mask_relpath,
    read_image,
    read_mask_file,
)
from framework.interfaces import BodyModel, MultiViewDataset

ROTATION_TOL = 1e-3  # |R R^T - I| and |det R - 1| a calibration rotation may be off by (float32 exports, rounding)


# ----------------------------------------------------------------------------------------------------------- reader
@dataclass
class ZjuCameras:
    """The rig exactly as stored (float64, OpenCV pixel convention, T in mm), plus converted views of it."""

    K: np.ndarray  # [C, 3, 3] OpenCV convention (pixel centres at integers)
    D: np.ndarray  # [C, 5] distortion (k1, k2, p1, p2, k3), zero-padded
    R: np.ndarray  # [C, 3, 3]
    T_mm: np.ndarray  # [C, 3]

    @classmethod
    def from_metres(cls, K: np.ndarray, D: np.ndarray, R: np.ndarray, T_m: np.ndarray) -> ZjuCameras:
        """The same rig from a translation in metres (EasyMocap's extri.yml), K in OpenCV's convention."""
        return cls(K=K, D=D, R=R, T_mm=np.asarray(T_m, dtype=np.float64) * 1000.0)

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

    def check(self, where: str | os.PathLike) -> None:
        """Every camera has a rotation R (orthonormal, det +1, within ROTATION_TOL) and positive focal lengths."""
        for c in range(self.num):
            R, K = self.R[c], self.K[c]
            off = float(np.abs(R @ R.T - np.eye(3)).max())
            det = float(np.linalg.det(R))
            if off > ROTATION_TOL or abs(det - 1.0) > ROTATION_TOL:
                raise ZjuFormatError(
                    f"{where}: the rotation R of camera {c} is not a rotation (|R R^T - I| = {off:.3g}, det = "
                    f"{det:.3g}); expected an orthonormal world-to-camera rotation with det +1. Export the calibration "
                    f"again (a scaled or mirrored R is not a camera pose)."
                )
            fx, fy = float(K[0, 0]), float(K[1, 1])
            if fx <= 0 or fy <= 0 or np.abs(K[2] - [0.0, 0.0, 1.0]).max() > 1e-6:
                raise ZjuFormatError(
                    f"{where}: the intrinsics K of camera {c} have fx = {fx:g}, fy = {fy:g}, last row "
                    f"{K[2].tolist()}; expected positive focal lengths in pixels, K = [[fx, 0, cx], [0, fy, cy], "
                    f"[0, 0, 1]]."
                )

    def K_splatrig(self) -> np.ndarray:
        """K with pixel centres at (j + 0.5, i + 0.5), the convention of framework.types / the rasterizers."""
        K = self.K.copy()
        K[:, 0, 2] += 0.5
        K[:, 1, 2] += 0.5
        return K


class ZjuSequence:
    """Lazy reader of one sequence: parses annots.npy; images, masks, params and vertices are read on demand."""

    def __init__(self, root: str | os.PathLike, params_dir: str = "auto", vertices_dir: str = "auto") -> None:
        """`params_dir` / `vertices_dir`: folders under root ("auto": params/ or new_params/, vertices/ or
        new_vertices/), e.g. the synthetic studio's ground_truth/params with the poses it was rendered from."""
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
        self.camera_names = [os.path.basename(d) or d for d in self.camera_dirs]
        self.file_numbers = [frame_number_from_path(row[0]) for row in self.ims]
        self.params_dir = self._folder(params_dir, PARAMS_DIRS, "params_dir")
        self.vertices_dir = self._folder(vertices_dir, VERTICES_DIRS, "vertices_dir")

    def _folder(self, name: str, auto: tuple[str, ...], key: str) -> str | None:
        """The folder `name` under root, or with "auto" the first of `auto` that exists (None: none does)."""
        if name == "auto":
            return next((d for d in auto if (self.root / d).is_dir()), None)
        if not (self.root / name).is_dir():
            raise ZjuMissingFileError(f"{key}={name}: {self.root / name} is not a folder; use {key}=auto")
        return name

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
        cameras = ZjuCameras(K=K, D=D, R=R, T_mm=T)
        cameras.check(path)
        return cameras

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

    def read_mask(self, path: Path) -> np.ndarray:
        """uint8 [H, W] in {0, 1}: the first stored channel is non-zero (Animatable NeRF's reading)."""
        return read_mask_file(path)

    def mask(self, frame: int, view: int, mask_dir: str = "auto") -> np.ndarray:
        """uint8 [H, W] in {0, 1}."""
        return self.read_mask(self.mask_path(frame, view, mask_dir))

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
def check_body_compatible(dataset: MultiViewDataset, body: BodyModel) -> None:
    """Stop before training when the stored poses cannot drive `body` (different joint count).

    The message names the params file (of a ZJU-layout sequence, else the dataset's root), the body and the fix.
    """
    poses = dataset.poses()
    if poses is None:
        return
    J_data = int(poses.shape[1])
    J_body = int(body.num_joints)
    if J_data == J_body:
        return
    where = dataset.root or "the dataset"
    seq = getattr(dataset, "seq", None)  # a ZJU-layout sequence names the params file of its first frame
    if seq is not None and dataset.frame_ids:
        try:
            where = seq.params_path(dataset.frame_ids[0])
        except FileNotFoundError:
            pass
    body_name = body.registry_name or type(body).__name__
    stored = dataset.body_name
    raise ZjuFormatError(
        f"{where}: stored poses have {J_data} joints ({J_data * 3} values per frame) but body model '{body_name}' has "
        f"{J_body} joints. The poses were made for body '{stored}'; select that body (body={stored}) or convert the "
        f"poses."
    )
