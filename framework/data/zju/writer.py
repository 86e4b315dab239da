"""Writes a sequence in the ZJU-MoCap layout (`framework.data.zju.layout` documents it); the synthetic studio and
the EasyMocap converter write through it."""

from __future__ import annotations

import os
import shutil
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from framework.atomic import atomic_path
from framework.data.zju.layout import (
    ANNOTS,
    MASK_DIRS,
    image_relpath,
    load_pickled_dict,
    mask_relpath,
    normalize_params,
    save_pickled_dict,
    write_image,
)


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

    DONE = ".frames_done"

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
            write_image(self.root / self.image_path(frame, v), images[v], self.jpeg_quality)
        self._write_masks_and_body(frame, masks, params, vertices)

    def copy_frame(
        self,
        frame: int,
        image_files: Sequence[str | os.PathLike],  # [C] encoded images, copied byte for byte (no re-encoding)
        masks: np.ndarray,  # [C, H, W] uint8 / bool, foreground non-zero
        params: dict | None = None,
        vertices: np.ndarray | None = None,
    ) -> None:
        """`write_frame` for images that are already files with this writer's extension (lossless conversion)."""
        if len(image_files) != self.num_cameras:
            raise ValueError(f"frame {frame}: {len(image_files)} image files for {self.num_cameras} cameras")
        for v, src in enumerate(image_files):
            if Path(src).suffix.lower() != self.image_ext.lower():
                raise ValueError(f"frame {frame}: {src} is not a {self.image_ext} file; copy_frame does not re-encode")
            with atomic_path(self.root / self.image_path(frame, v)) as tmp:
                shutil.copyfile(src, tmp)
        self._write_masks_and_body(frame, np.asarray(masks), params, vertices)

    def write_masks(self, frame: int, masks: np.ndarray, mask_dir: str) -> None:
        """Masks [C, H, W] (foreground non-zero) of one frame into `mask_dir` (e.g. a second, parser-made set in
        mask_cihp/ next to mask/, as ZJU-MoCap ships both). Written atomically; write them before `write_frame` /
        `copy_frame` of the same frame, which marks the frame done."""
        if mask_dir not in MASK_DIRS:
            raise ValueError(f"mask_dir must be one of {MASK_DIRS}, got '{mask_dir}'")
        for v in range(self.num_cameras):
            m = (np.asarray(masks[v]) != 0).astype(np.uint8) * np.uint8(self.mask_value)
            write_image(self.root / mask_dir / mask_relpath(self.image_path(frame, v)), m)

    def _write_masks_and_body(
        self, frame: int, masks: np.ndarray, params: dict | None, vertices: np.ndarray | None
    ) -> None:
        self.write_masks(frame, masks, self.mask_dir)
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
