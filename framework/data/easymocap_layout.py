"""EasyMocap's output layout (zju3dv/EasyMocap), read as EasyMocap writes it: a lazy `EasyMocapSequence`.

    <root>/
      intri.yml   OpenCV FileStorage (EasyMocap's own writer starts "%YAML:1.0"; cv2's "%YAML 1.2"; both read):
                    names: ["01", "02", ...]          the cameras, in order (an unquoted number reads as its digits)
                    K_<name>: 3x3                     OpenCV pixel convention: pixel (i, j) has its centre at (j, i)
                    dist_<name>: 1x5                  k1 k2 p1 p2 k3 (older files: D_<name>); may be missing = none
                    H_<name>, W_<name>                optional image size (checked against the images when present)
      extri.yml   names (the same cameras)
                    R_<name>: 3x1                     Rodrigues vector; easymocap/mytools/camera_utils.py read_camera
                                                      applies cv2.Rodrigues (a 3x3 matrix here is accepted too)
                    Rot_<name>: 3x3                   the same rotation as a matrix (write_camera writes both);
                                                      used when R_ is missing, checked against R_ when both are there
                    T_<name>: 3x1                     METRES; world-to-camera: x_cam = R x_world + T
      images/<name>/NNNNNN.jpg     frames (scripts/preprocess/extract_video.py). As EasyMocap's MVBase: frame i is
                                   the i-th file of each camera's sorted listing, and a camera with more frames than
                                   the others is cut to the shortest; a frame whose file names differ between cameras
                                   (a dropped frame, so the cameras fall out of step) is an error
      mask/<name>/NNNNNN.png       foreground masks, or mask-schp/<name>/NNNNNN.png (SCHP part labels as a palette
                                   PNG, background 0): foreground wherever any channel is non-zero, as EasyMocap's
                                   neuralbody reader takes grey > 0. Its reader also accepts NNNNNN_0.png; so do we.
      output*/smpl/NNNNNN.json     apps/demo/mv1p.py --out <out> writes <out>/smpl/ (so --out output/smpl gives
                                   output/smpl/smpl/), named by the frame's POSITION ({i:06d}, MVBase.basename; the
                                   image's own name when no 000000.json exists but that name does); a list of people
                                   (or {"annots": [...]}), each
                                   {"id": 0, "Rh": [[3]], "Th": [[3]], "poses": [[72 | 87 | 165]], "shapes": [[10]],
                                    "expression": [[10]] (SMPL-X)}
      output*/vertices/NNNNNN.json (--write_vertices) [{"id": 0, "vertices": [[x, y, z], ...]}], world metres

Body parameters (easymocap/smplmodel/body_model.py, doc/02_output.md): world vertices = R(Rh) · M(poses, shapes) + Th,
the rotation about the ORIGIN; EasyMocap keeps poses[:3] at zero and carries the root in Rh / Th. Poses are
absolute axis-angle rotations (no mean pose is added: `use_flat_mean`). SMPL: 72 = 24 joints. SMPL-X: 87 = 66 body
(22 joints, root slot first) + 6 left-hand + 6 right-hand PCA coefficients + 9 head (jaw, left eye, right eye); the
hand coefficients multiply the first 6 rows of the model file's `hands_componentsl` / `hands_componentsr` and the
result is ordered as the SMPL-X skeleton: body 66, jaw, left eye, right eye, left hand 45, right hand 45 = 165
(SMPLlayer.extend_pose); files that hold the 165 values already are read as they are. The expansion needs the
SMPL-X file EasyMocap fitted with. SMPL+H (78 values) is not supported. Expression coefficients are read and kept,
not used by bodies.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np

from framework.data.zju.layout import read_image, read_mask_file
from framework.data.zju.reader import ZjuCameras
from framework.errors import SplatrigError

INTRI, EXTRI = "intri.yml", "extri.yml"
IMAGE_DIR = "images"
MASK_DIRS = ("mask", "mask-schp")
IMAGE_EXTS = (".jpg", ".jpeg", ".png")
SMPL_POSES, SMPLX_PCA_POSES, SMPLX_FULL_POSES, SMPLH_PCA_POSES = 72, 87, 165, 78
HAND_PCA = 6


class EasyMocapError(SplatrigError, ValueError):
    """An EasyMocap folder that does not follow the layout; the message names the file, what was expected and found."""


class EasyMocapFileMissing(SplatrigError, FileNotFoundError):
    """A file or folder the layout needs is not there; the message names it and what to run or set."""


# ----------------------------------------------------------------------------------------------------------- cameras
def _read_names(fs, path: Path) -> list[str]:
    """EasyMocap's FileStorage.read(dt='list'): strings, numbers as their integer digits, 'none' skipped."""
    node = fs.getNode("names")
    if node.empty() or not node.isSeq():
        raise EasyMocapError(f"{path}: expected a 'names' list of camera names (as EasyMocap's write_camera writes)")
    names = []
    for i in range(node.size()):
        item = node.at(i)
        name = item.string() if item.isString() else str(int(item.real()))
        if name != "none":
            names.append(name)
    if not names:
        raise EasyMocapError(f"{path}: the 'names' list is empty; expected one entry per camera")
    return names


def _matrix(fs, key: str, name: str) -> np.ndarray | None:
    """The matrix stored under `key` (also under the name cut at its first '.', as EasyMocap writes keys)."""
    for k in (key.format(name), key.format(name.split(".")[0])):
        node = fs.getNode(k)
        if not node.empty():
            return np.asarray(node.mat(), dtype=np.float64)
    return None


def read_easymocap_cameras(root: Path) -> tuple[list[str], ZjuCameras, list[tuple[int, int] | None]]:
    """Camera names (intri.yml order), the rig (T in metres stored as ZjuCameras) and the optional (W, H) per camera."""
    import cv2

    paths = {n: root / n for n in (INTRI, EXTRI)}
    for p in paths.values():
        if not p.is_file():
            raise EasyMocapFileMissing(
                f"{p} is missing: expected EasyMocap's calibration ({INTRI} with K_<cam>/dist_<cam>, {EXTRI} with "
                f"R_<cam>/T_<cam>) at the root of the capture; check data.root (found {_listing(root)})"
            )
    fs_in = cv2.FileStorage(str(paths[INTRI]), cv2.FILE_STORAGE_READ)
    fs_ex = cv2.FileStorage(str(paths[EXTRI]), cv2.FILE_STORAGE_READ)
    try:
        names = _read_names(fs_in, paths[INTRI])
        extri_names = _read_names(fs_ex, paths[EXTRI])
        K, D, R, T, sizes = [], [], [], [], []
        for name in names:
            k = _matrix(fs_in, "K_{}", name)
            if k is None or k.shape != (3, 3):
                raise EasyMocapError(f"{paths[INTRI]}: camera '{name}' needs K_{name} (3x3), found {_shape(k)}")
            dist = _matrix(fs_in, "dist_{}", name)
            dist = _matrix(fs_in, "D_{}", name) if dist is None else dist
            d = np.zeros(5)
            if dist is not None:
                d[: min(5, dist.size)] = dist.ravel()[:5]
            rvec = _matrix(fs_ex, "R_{}", name)
            rot = _matrix(fs_ex, "Rot_{}", name)
            t = _matrix(fs_ex, "T_{}", name)
            if (rvec is None and rot is None) or t is None or t.size != 3:
                listed = "" if name in extri_names else f" ('{name}' is not even in its names list {extri_names})"
                raise EasyMocapError(
                    f"{paths[EXTRI]}: camera '{name}' (listed in {INTRI}) needs R_{name} (3x1 Rodrigues) or "
                    f"Rot_{name} (3x3) and T_{name} (3x1, metres); found R {_shape(rvec)}, Rot {_shape(rot)}, "
                    f"T {_shape(t)}{listed}"
                )
            r = _rotation(rvec, rot, name, paths[EXTRI])
            for what, arr in (("K", k), ("dist", d), ("R", r), ("T", t)):
                if not np.isfinite(arr).all():
                    raise EasyMocapError(
                        f"{paths[INTRI if what in ('K', 'dist') else EXTRI]}: {what}_{name} has non-finite values"
                    )
            K.append(k), D.append(d), R.append(r), T.append(t.ravel())
            h, w = fs_in.getNode(f"H_{name}"), fs_in.getNode(f"W_{name}")
            sizes.append(None if h.empty() or w.empty() else (int(w.real()), int(h.real())))
    finally:
        fs_in.release()
        fs_ex.release()
    cams = ZjuCameras.from_metres(np.stack(K), np.stack(D), np.stack(R), np.stack(T))
    return names, cams, sizes


def _rotation(rvec: np.ndarray | None, rot: np.ndarray | None, name: str, path: Path) -> np.ndarray:
    """R_<name> (Rodrigues vector, or a matrix) wins as in EasyMocap's read_camera; Rot_<name> when R_ is missing."""
    import cv2

    r = None
    if rvec is not None:
        if rvec.size == 3:
            r = cv2.Rodrigues(rvec.reshape(3, 1))[0]
        elif rvec.shape == (3, 3):
            r = rvec
        else:
            raise EasyMocapError(f"{path}: R_{name} must be a 3x1 Rodrigues vector or a 3x3 matrix, found {rvec.shape}")
    if rot is not None:
        if rot.shape != (3, 3):
            raise EasyMocapError(f"{path}: Rot_{name} must be 3x3, found {rot.shape}")
        if r is None:
            r = rot
        elif np.abs(r - rot).max() > 1e-4:
            raise EasyMocapError(
                f"{path}: R_{name} (Rodrigues) and Rot_{name} describe different rotations (max difference "
                f"{np.abs(r - rot).max():.3g}); EasyMocap uses R_{name}: delete Rot_{name} or fix the one that is wrong"
            )
    assert r is not None
    if abs(np.linalg.det(r) - 1.0) > 1e-3 or np.abs(r @ r.T - np.eye(3)).max() > 1e-3:
        raise EasyMocapError(
            f"{path}: the rotation of camera '{name}' is not a rotation (det {np.linalg.det(r):.4f}); expected "
            f"R_{name} as a Rodrigues vector or an orthonormal 3x3 matrix"
        )
    return r


def _shape(a: np.ndarray | None) -> str:
    return "nothing" if a is None else "x".join(str(n) for n in a.shape)


def _listing(root: Path) -> str:
    if not root.exists():
        return "the directory does not exist"
    names = sorted(p.name for p in root.iterdir())[:10]
    return ", ".join(names) if names else "an empty directory"


# ----------------------------------------------------------------------------------------------------------- poses
def expand_smplx_hand_pca(poses: np.ndarray, left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """EasyMocap's SMPL-X poses [..., 87] (body 66, left PCA 6, right PCA 6, head 9) -> [..., 165] in skeleton order
    (body 66, jaw / eyes 9, left hand 45, right hand 45); `left` / `right` [6, 45] are the PCA bases (flat mean)."""
    poses = np.asarray(poses, dtype=np.float64)
    body = poses[..., :66]
    lh = poses[..., 66 : 66 + HAND_PCA] @ left
    rh = poses[..., 66 + HAND_PCA : 66 + 2 * HAND_PCA] @ right
    head = poses[..., 66 + 2 * HAND_PCA :]
    return np.concatenate([body, head, lh, rh], axis=-1)


def body_of_pose_length(n: int) -> str | None:
    """The body model EasyMocap writes `n` pose values for (None: not one of its models)."""
    return {SMPL_POSES: "smpl", SMPLX_PCA_POSES: "smplx", SMPLX_FULL_POSES: "smplx", SMPLH_PCA_POSES: "smplh"}.get(n)


def read_people(path: Path) -> list[dict]:
    """The people of one EasyMocap JSON file (a list, or {"annots": [...]}); ids from "id" or "personID"."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise EasyMocapError(f"{path}: cannot be read as JSON ({type(exc).__name__}: {exc})") from exc
    if isinstance(data, dict):
        data = data.get("annots", [data])
    if not isinstance(data, list) or not all(isinstance(d, dict) for d in data):
        raise EasyMocapError(
            f"{path}: expected a list of people ({{'id': ..., 'Rh': ...}}), found {type(data).__name__}"
        )
    for d in data:
        if "id" not in d and "personID" in d:
            d["id"] = d["personID"]
    return data


# ----------------------------------------------------------------------------------------------------------- reader
class EasyMocapSequence:
    """Lazy reader of one EasyMocap capture; the same interface as ZjuSequence (framework.data.sequence_dataset).

    `cameras`: camera names to use, in this order (None: intri.yml's list). `mask_dir`, `params_dir`,
    `vertices_dir`: "auto" finds them (see `find_*`), or a folder relative to the root (vertices: also None).
    `person_id`: whose parameters to read when the files hold several people. `smplx_model_path` / `smplx_gender`:
    the SMPL-X file (or its folder) whose hand PCA bases expand 87-value poses; looked up only when such poses appear.
    """

    def __init__(
        self,
        root: str | os.PathLike,
        cameras: list[str] | None = None,
        mask_dir: str = "auto",
        params_dir: str = "auto",
        vertices_dir: str | None = "auto",
        person_id: int | None = None,
        smplx_model_path: str | None = None,
        smplx_gender: str = "neutral",
    ) -> None:
        self.root = Path(root)
        names, cams, sizes = read_easymocap_cameras(self.root)
        if cameras is not None:
            cameras = [str(c) for c in cameras]
            unknown = [c for c in cameras if c not in names]
            if unknown:
                raise EasyMocapError(
                    f"{self.root / INTRI}: data.cameras lists {unknown} but the calibration names {names}; "
                    f'quote camera names in YAML ("01", not 01)'
                )
            pick = [names.index(c) for c in cameras]
            cams = ZjuCameras(K=cams.K[pick], D=cams.D[pick], R=cams.R[pick], T_mm=cams.T_mm[pick])
            names, sizes = cameras, [sizes[i] for i in pick]
        self.camera_names = names
        self.cameras = cams
        self.image_sizes = sizes
        self.camera_dirs = [f"{IMAGE_DIR}/{n}" for n in names]
        self._files = self._find_frames()  # [C][F] image file names
        self.stems = [os.path.splitext(n)[0] for n in self._files[0]]
        self.mask_dir = self.find_mask_dir(mask_dir)
        self.params_dir = self.find_params_dir(params_dir)
        self.vertices_dir = self.find_vertices_dir(vertices_dir)
        self.fit_names = self._fit_names()
        self.person_id = person_id
        self.smplx_model_path = smplx_model_path
        self.smplx_gender = smplx_gender
        self._hand_pca: tuple[np.ndarray, np.ndarray] | None = None

    # -------------------------------------------------------------------------------------------------- discovery
    def _find_frames(self) -> list[list[str]]:
        """Each camera's sorted image files, cut to the shortest camera (EasyMocap's MVBase does the same)."""
        images = self.root / IMAGE_DIR
        per_cam: list[list[str]] = []
        for name in self.camera_names:
            folder = images / name
            if not folder.is_dir():
                present = sorted(p.name for p in images.iterdir() if p.is_dir()) if images.is_dir() else []
                raise EasyMocapFileMissing(
                    f"{folder} is missing: {INTRI} names camera '{name}' but there is no image folder for it "
                    f"(found {present or 'no images/ folder'}); extract the videos with EasyMocap's "
                    f"scripts/preprocess/extract_video.py, or list the cameras to use in data.cameras"
                )
            files = sorted(n for n in os.listdir(folder) if os.path.splitext(n)[1].lower() in IMAGE_EXTS)
            if not files:
                raise EasyMocapFileMissing(f"{folder} holds no images (expected NNNNNN.jpg)")
            per_cam.append(files)
        n = min(len(f) for f in per_cam)
        stems = [[os.path.splitext(x)[0] for x in files[:n]] for files in per_cam]
        for name, own in zip(self.camera_names[1:], stems[1:], strict=True):
            if own != stems[0]:
                i = next(k for k in range(n) if own[k] != stems[0][k])
                raise EasyMocapError(
                    f"{images / name}: frame {i} is {own[i]} but in {images / self.camera_names[0]} it is "
                    f"{stems[0][i]}; the cameras are out of step (a dropped or extra frame): every camera needs the "
                    f"same, synchronised frame names"
                )
        if any(len(f) != n for f in per_cam):
            counts = {name: len(f) for name, f in zip(self.camera_names, per_cam, strict=True) if len(f) != n}
            print(
                f"[splatrig] easymocap: using the first {n} frames of every camera, as EasyMocap does ({counts} "
                f"hold more)",
                file=sys.stderr,
            )
        return [files[:n] for files in per_cam]

    def _fit_names(self) -> list[str]:
        """The JSON name of each frame's fit: its position (EasyMocap's mv1p), or its image name when the fits
        are named that way (no 000000.json but a file for the first image's name)."""
        positions = [f"{i:06d}" for i in range(len(self.stems))]
        if positions == self.stems or (self.params_dir / "000000.json").exists():
            return positions
        if (self.params_dir / f"{self.stems[0]}.json").exists():
            return list(self.stems)
        return positions

    def available_mask_dirs(self) -> list[str]:
        return [d for d in MASK_DIRS if (self.root / d).is_dir()]

    def find_mask_dir(self, mask_dir: str) -> str:
        """ "auto": mask/ when it exists, else mask-schp/; or the folder named (relative to the root)."""
        if mask_dir != "auto":
            if not (self.root / mask_dir).is_dir():
                raise EasyMocapFileMissing(
                    f"{self.root / mask_dir} does not exist (data.mask_dir='{mask_dir}'); found "
                    f"{self.available_mask_dirs() or 'no mask folder'}; use data.mask_dir=auto"
                )
            return mask_dir
        found = self.available_mask_dirs()
        if not found:
            raise EasyMocapFileMissing(
                f"{self.root}: no mask folder: expected mask/<cam>/NNNNNN.png or mask-schp/<cam>/NNNNNN.png (one "
                f"foreground mask per image, e.g. from SCHP; see docs/own_capture.md); found {_listing(self.root)}"
            )
        return found[0]

    def find_params_dir(self, params_dir: str) -> Path:
        """ "auto": the single output*/smpl or output*/*/smpl folder holding NNNNNN.json files."""
        if params_dir != "auto":
            path = self.root / params_dir
            if not path.is_dir():
                raise EasyMocapFileMissing(f"{path} does not exist (data.params_dir='{params_dir}')")
            return path
        found = sorted(
            {p.parent for pattern in ("output*/smpl/*.json", "output*/*/smpl/*.json") for p in self.root.glob(pattern)}
        )
        if not found:
            raise EasyMocapFileMissing(
                f"{self.root}: no SMPL parameters: expected output*/smpl/NNNNNN.json (EasyMocap's apps/demo/mv1p.py "
                f"--out {self.root}/output writes them); found {_listing(self.root)}; or set data.params_dir"
            )
        if len(found) > 1:
            rel = [str(p.relative_to(self.root)) for p in found]
            raise EasyMocapError(
                f"{self.root}: several parameter folders {rel}; choose one with data.params_dir={rel[0]}"
            )
        return found[0]

    def find_vertices_dir(self, vertices_dir: str | None) -> Path | None:
        """ "auto": `vertices/` next to the parameters' `smpl/` folder (mv1p.py --write_vertices), else None."""
        if vertices_dir is None:
            return None
        if vertices_dir != "auto":
            path = self.root / vertices_dir
            if not path.is_dir():
                raise EasyMocapFileMissing(f"{path} does not exist (data.vertices_dir='{vertices_dir}')")
            return path
        path = self.params_dir.parent / "vertices"
        return path if path.is_dir() else None

    # -------------------------------------------------------------------------------------------------- access
    @property
    def num_frames(self) -> int:
        return len(self.stems)

    @property
    def num_views(self) -> int:
        return len(self.camera_names)

    def image_path(self, frame: int, view: int) -> Path:
        return self.root / IMAGE_DIR / self.camera_names[view] / self._files[view][frame]

    def image(self, frame: int, view: int) -> np.ndarray:
        """uint8 [H, W, 3] RGB, as stored (distorted); checks the size intri.yml states, when it states one."""
        img = read_image(self.image_path(frame, view))
        size = self.image_sizes[view]
        if size is not None and size != (img.shape[1], img.shape[0]):
            name = self.camera_names[view]
            raise EasyMocapError(
                f"{self.image_path(frame, view)}: image is {img.shape[1]}x{img.shape[0]} but {INTRI} gives "
                f"W_{name} x H_{name} = {size[0]}x{size[1]}; K belongs to that size: use the original images or "
                f"rescale K and fix W/H"
            )
        return img

    def mask_path(self, frame: int, view: int, mask_dir: str = "auto") -> Path:
        folder = self.root / (self.mask_dir if mask_dir == "auto" else mask_dir) / self.camera_names[view]
        stem = self.stems[frame]
        candidates = [folder / f"{stem}.png", folder / f"{stem}_0.png", folder / f"{stem}.jpg"]
        for c in candidates:
            if c.exists():
                return c
        raise EasyMocapFileMissing(
            f"mask of frame {frame} ({stem}), camera '{self.camera_names[view]}' is missing: looked for "
            f"{', '.join(str(c) for c in candidates)}"
        )

    def read_mask(self, path: Path) -> np.ndarray:
        """uint8 [H, W] in {0, 1}: foreground wherever any channel is non-zero (SCHP's palette labels included)."""
        return read_mask_file(path, any_channel=True)

    def mask(self, frame: int, view: int) -> np.ndarray:
        return self.read_mask(self.mask_path(frame, view))

    def params_path(self, frame: int) -> Path:
        path = self.params_dir / f"{self.fit_names[frame]}.json"
        if not path.exists():
            raise EasyMocapFileMissing(
                f"params of frame {frame} is missing: expected {path} (EasyMocap writes one JSON per frame; frame "
                f"{frame} ({self.stems[frame]}) has images but no fit)"
            )
        return path

    def _person(self, path: Path, kind: str) -> dict:
        people = read_people(path)
        ids = [d.get("id") for d in people]
        if self.person_id is None:
            if len(people) != 1:
                raise EasyMocapError(
                    f"{path}: holds {len(people)} people (ids {ids}); choose one with data.person_id=<id>"
                )
            return people[0]
        for d in people:
            if d.get("id") == self.person_id:
                return d
        raise EasyMocapError(
            f"{path}: no person with id {self.person_id} (data.person_id) in this {kind} file; ids here: {ids}"
        )

    def params(self, frame: int) -> dict:
        """poses [1, J*3] (SMPL-X hand PCA expanded), Rh [1, 3], Th [1, 3], shapes [1, S], expression, body."""
        path = self.params_path(frame)
        p = self._person(path, "parameter")
        missing = [k for k in ("Rh", "Th", "poses") if k not in p]
        if missing:
            raise EasyMocapError(
                f"{path}: expected keys Rh, Th, poses (and shapes), missing {missing}; found {sorted(p)}"
            )
        out = {k: np.asarray(p[k], dtype=np.float32).reshape(1, -1) for k in ("Rh", "Th", "poses")}
        out["shapes"] = np.asarray(p.get("shapes", np.zeros(10)), dtype=np.float32).reshape(1, -1)
        if "expression" in p:
            out["expression"] = np.asarray(p["expression"], dtype=np.float32).reshape(1, -1)
        n = out["poses"].shape[1]
        body = body_of_pose_length(n)
        if body == "smplh":
            raise EasyMocapError(
                f"{path}: poses hold {n} values (SMPL+H with hand PCA), which splatrig does not read; fit SMPL "
                f"(--model smpl) or SMPL-X (--model smplx) with EasyMocap"
            )
        if n == SMPLX_PCA_POSES:
            out["poses"] = expand_smplx_hand_pca(out["poses"], *self.hand_pca(path)).astype(np.float32)
        if body is not None:
            out["body"] = body
        return out

    def hand_pca(self, needed_by: Path) -> tuple[np.ndarray, np.ndarray]:
        """The SMPL-X hand PCA bases [6, 45] (left, right), read once from `smplx_model`."""
        if self._hand_pca is None:
            if self.smplx_model_path in (None, ""):
                raise EasyMocapError(
                    f"{needed_by}: poses hold {SMPLX_PCA_POSES} values (SMPL-X with {HAND_PCA} hand PCA coefficients "
                    f"per hand); expanding them needs the SMPL-X model file EasyMocap fitted with: pass body=smplx "
                    f"body.model_path=/path/to/SMPLX_<GENDER>.pkl (or data.body_model_path)"
                )
            from framework.bodies.model_files import hand_pca_components, resolve_model_file

            model = resolve_model_file(self.smplx_model_path, "smplx", self.smplx_gender)
            self._hand_pca = hand_pca_components(model, HAND_PCA)
        return self._hand_pca

    def vertices_path(self, frame: int) -> Path:
        if self.vertices_dir is None:
            raise EasyMocapFileMissing(f"vertices of frame {frame}: no vertices/ folder next to {self.params_dir}")
        path = self.vertices_dir / f"{self.fit_names[frame]}.json"
        if not path.exists():
            raise EasyMocapFileMissing(f"vertices of frame {frame} are missing: expected {path}")
        return path

    def vertices(self, frame: int) -> np.ndarray:
        """[V, 3] float32 posed world vertices."""
        path = self.vertices_path(frame)
        v = np.asarray(self._person(path, "vertices").get("vertices", []), dtype=np.float32)
        if v.ndim != 2 or v.shape[1] != 3 or not len(v):
            raise EasyMocapError(f"{path}: expected 'vertices' [V, 3], found shape {v.shape}")
        return v
