"""Dataset `zju_mocap`: ZJU-MoCap, H36M and CMU Panoptic sequences in the Neural Body / Animatable NeRF layout
(and the synthetic studio, written in the same layout). The layout itself is documented in
`framework.data.zju_format`.

What a sample is: one (frame, view) pair of the split, as a FrameBatch with B = 1.
- Image: decoded on access (never all images as float32), undistorted with cv2's undistort maps (D applied, K kept,
  as Neural Body / Animatable NeRF do), downscaled with INTER_AREA, composited over a black (or white) background with
  the mask (Animatable NeRF's `mask_bkgd`), float32 in [0, 1]. An optional LRU cache keeps processed uint8 images.
- Mask: foreground = stored value != 0, undistorted and area-downscaled like the image (fractional at the edge).
- Boundary M_b: 0 within `boundary_px` output pixels of the silhouette (mask >= 0.5), computed once per (frame, view)
  and cached in memory (bit-packed) and optionally on disk.
- Cameras: K converted from OpenCV's pixel convention (centres at integers) to ours (centres at j + 0.5): cx += 0.5,
  cy += 0.5; then for a downscale to W' x H', K'[0] = K[0] * W'/W and K'[1] = K[1] * H'/H. In the half-pixel convention
  a pure scaling of image coordinates is exact for area resampling (output pixel j' covers input [s j', s j' + s),
  centred at s (j' + 0.5)); the same formula in OpenCV's convention would be cx' = (cx + 0.5) / s - 0.5.
  world_to_cam = [[R, T / 1000], [0, 1]] (T is stored in millimetres).
- Body: pose = params["poses"] reshaped [J, 3] (the global-orient slot kept as stored), root = [[R(Rh), Th], [0, 1]]
  (EasyMocap: world = R(Rh) M(pose, shapes) + Th about the origin), betas = params["shapes"].
- bounds: the world-space box of the stored posed vertices (vertices/) over the split's frames, grown by
  `bounds_margin` metres on every side. The body model is not known here, so this is not a canonical box; without
  vertices/ it falls back to the Th positions grown by 1.2 m.

Protocols (`protocol=`): presets that make results comparable with published tables.
- "aninerf_4view": Animatable NeRF (zju3dv/animatable_nerf, configs/aninerf_{313,315,377,386}.yaml and
  configs/aligned_nerf_pdf/aligned_aninerf_pdf_{387,390,392,393,394}.yaml;
  H36M: configs/aninerf_s{1,5,6,7,8,9,11}p.yaml):
  ZJU training views [0, 6, 12, 18], test views = every other view; H36M training views [0, 1, 2], test view [3].
  Training frames begin_ith_frame + k * frame_interval for k < num_train_frame; novel-pose frames follow the training
  frames (num_eval_frame of them; CoreView_390 evaluates novel poses from frame 0). Evaluation takes every 30th frame of
  the split's frame list (their test FrameSampler, `cfg.test.frame_sampler_interval = 30`).
- "dense": every view except the held-out views {v : v % 6 == 3} (3, 9, 15, 21 on a 23-camera rig) for training; those
  held-out views for testing; frames as in "aninerf_4view". There is no single published dense-view protocol for
  these data; this one is ours and keeps a held-out view in each quarter of the ring.
- None: everything from the explicit arguments (train_views / test_views / train_frames / novel_pose_frames).
Explicit arguments always override the preset's values.
"""

from __future__ import annotations

import logging
import os
import re
from collections import OrderedDict
from pathlib import Path
from typing import Any

import numpy as np
import torch

from framework.atomic import atomic_path
from framework.data.boundary import boundary_mask
from framework.data.zju_format import ZjuFormatError, ZjuMissingFileError, ZjuSequence, check_body_compatible
from framework.interfaces import MultiViewDataset
from framework.registry import register
from framework.types import Cameras, FrameBatch

__all__ = ["ZjuMocapDataset", "check_body_compatible", "PROTOCOL_FRAMES"]

log = logging.getLogger(__name__)

# sequence -> (begin_ith_frame, num_train_frame, frame_interval, num_eval_frame, novel_pose_begin or None)
PROTOCOL_FRAMES: dict[str, tuple[int, int, int, int, int | None]] = {
    "313": (0, 60, 1, 1000, None),
    "315": (0, 400, 1, 1000, None),
    "377": (0, 300, 1, 200, None),
    "386": (0, 300, 1, 346, None),
    "387": (0, 300, 1, 1000, None),
    "390": (700, 300, 1, 700, 0),
    "392": (0, 300, 1, 1000, None),
    "393": (0, 300, 1, 1000, None),
    "394": (0, 300, 1, 1000, None),
    "S1": (0, 150, 5, 49, None),
    "S5": (0, 250, 5, 127, None),
    "S6": (0, 150, 5, 83, None),
    "S7": (0, 300, 5, 200, None),
    "S8": (0, 250, 5, 87, None),
    "S9": (0, 260, 5, 133, None),
    "S11": (0, 200, 5, 82, None),
}
PROTOCOLS = ("aninerf_4view", "dense")
EVAL_FRAME_STEP = 30
SPLITS = ("train", "novel_view", "novel_pose")


def sequence_key(root: Path) -> str | None:
    """ "313" for .../CoreView_313, "S9" for .../S9/Posing; None when the path names no known sequence."""
    for part in reversed(root.resolve().parts):
        m = re.fullmatch(r"(?:CoreView_|my_)?(\d{3})", part)
        if m and m.group(1) in PROTOCOL_FRAMES:
            return m.group(1)
        if part in PROTOCOL_FRAMES:
            return part
    return None


def _frame_range(spec: Any, num_frames: int, what: str) -> list[int]:
    """(start, end, step) with end exclusive and clipped to the sequence; None = all frames; a list = those frames."""
    if spec is None:
        return list(range(num_frames))
    spec = list(spec)
    if len(spec) in (2, 3) and all(isinstance(x, (int, type(None))) for x in spec):
        start, end = spec[0] or 0, spec[1]
        step = spec[2] if len(spec) == 3 and spec[2] else 1
        end = num_frames if end is None else min(int(end), num_frames)
        frames = list(range(int(start), end, int(step)))
    else:
        frames = [int(x) for x in spec]
    bad = [f for f in frames if not 0 <= f < num_frames]
    if bad or not frames:
        raise ValueError(
            f"{what}={spec} selects {'no frames' if not frames else f'frames outside 0..{num_frames - 1}: {bad[:5]}'}"
            f" (the sequence has {num_frames} frames); give (start, end, step) with end exclusive"
        )
    return frames


class _LRU:
    """A byte-budgeted LRU for processed uint8 arrays."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self.bytes = 0
        self.items: OrderedDict[Any, tuple[np.ndarray, ...]] = OrderedDict()

    def get(self, key: Any) -> tuple[np.ndarray, ...] | None:
        if key in self.items:
            self.items.move_to_end(key)
            return self.items[key]
        return None

    def put(self, key: Any, value: tuple[np.ndarray, ...]) -> None:
        size = sum(v.nbytes for v in value)
        if size > self.max_bytes:
            return
        self.items[key] = value
        self.bytes += size
        while self.bytes > self.max_bytes:
            _, old = self.items.popitem(last=False)
            self.bytes -= sum(v.nbytes for v in old)


@register("dataset", "zju_mocap")
class ZjuMocapDataset(MultiViewDataset):
    """One split of a ZJU-MoCap-layout sequence; see the module docstring for conventions and protocols."""

    def __init__(
        self,
        root: str,
        split: str = "train",
        protocol: str | None = "aninerf_4view",
        sequence: str | None = None,
        train_views: list[int] | None = None,
        test_views: list[int] | None = None,
        novel_pose_views: list[int] | None = None,
        train_frames: Any = None,
        novel_pose_frames: Any = None,
        eval_frame_step: int | None = None,
        downscale: float = 1.0,
        boundary_px: int = 5,
        mask_dir: str = "auto",
        body: str | None = None,
        white_background: bool = False,
        mask_background: bool = True,
        bounds_margin: float = 0.1,
        cache_mb: float = 512.0,
        boundary_cache: str = "memory",
        cache_dir: str | None = None,
    ) -> None:
        super().__init__()
        if split not in SPLITS:
            raise ValueError(f"zju_mocap: split must be one of {SPLITS}, got '{split}'")
        if mask_dir not in ("auto", "mask", "mask_cihp"):
            raise ValueError(f"zju_mocap: mask_dir must be 'auto', 'mask' or 'mask_cihp', got '{mask_dir}'")
        if boundary_cache not in ("memory", "disk"):
            raise ValueError(f"zju_mocap: boundary_cache must be 'memory' or 'disk', got '{boundary_cache}'")
        if not downscale >= 1.0:
            raise ValueError(f"zju_mocap: downscale must be >= 1 (an image size divisor), got {downscale}")
        self.root = Path(os.path.expanduser(str(root)))
        self.seq = ZjuSequence(self.root)
        self.split = split
        self.downscale = float(downscale)
        self.boundary_px = int(boundary_px)
        self.mask_dir = mask_dir
        if mask_dir != "auto" and not (self.root / mask_dir).is_dir():
            raise ZjuMissingFileError(
                f"zju_mocap: mask_dir='{mask_dir}' but {self.root / mask_dir} does not exist; "
                f"found {self.seq.available_mask_dirs() or 'no mask folder'}; use mask_dir=auto"
            )
        self.background = 1.0 if white_background else 0.0
        self.mask_background = mask_background
        self.num_frames_total = self.seq.num_frames
        C = self.seq.num_views

        # ---- protocol
        self.sequence = sequence or sequence_key(self.root)
        views_all = list(range(C))
        preset_train_views: list[int] = views_all
        preset_train_frames: Any = None
        preset_pose_frames: Any = None
        preset_step = 1
        if protocol is not None:
            if protocol not in PROTOCOLS:
                raise ValueError(f"zju_mocap: unknown protocol '{protocol}'; known: {', '.join(PROTOCOLS)} or null")
            h36m = self.sequence is not None and self.sequence.startswith("S")
            if protocol == "aninerf_4view":
                preset_train_views = [0, 1, 2] if h36m else [0, 6, 12, 18]
            else:
                preset_train_views = [v for v in views_all if v % 6 != 3]
            preset_train_views = [v for v in preset_train_views if v < C]
            if self.sequence in PROTOCOL_FRAMES:
                b, n, step, ne, pose_begin = PROTOCOL_FRAMES[self.sequence]
                preset_train_frames = (b, b + n * step, step)
                pb = b + n * step if pose_begin is None else pose_begin
                preset_pose_frames = (pb, pb + ne * step, step)
                preset_step = EVAL_FRAME_STEP
            elif train_frames is None or (split == "novel_pose" and novel_pose_frames is None):
                raise ValueError(
                    f"zju_mocap: protocol '{protocol}' has frame numbers for {', '.join(PROTOCOL_FRAMES)} but "
                    f"{self.root} names none of them; pass sequence=<one of them>, or train_frames=[start, end, step] "
                    f"and novel_pose_frames=[start, end, step]"
                )
        self.train_views = list(train_views) if train_views is not None else preset_train_views
        # like Animatable NeRF: test views default to every view not trained on (view 0 when that leaves none)
        complement = [v for v in views_all if v not in self.train_views]
        self.test_views = list(test_views) if test_views is not None else (complement or [0])
        self.novel_pose_views = list(novel_pose_views) if novel_pose_views is not None else self.test_views
        for name, vs in (("train_views", self.train_views), ("test_views", self.test_views),
                         ("novel_pose_views", self.novel_pose_views)):  # fmt: skip
            bad = [v for v in vs if not 0 <= int(v) < C]
            if bad or not vs:
                raise ValueError(f"zju_mocap: {name}={vs} must be non-empty view indices in 0..{C - 1} ({self.root})")
        train_spec = train_frames if train_frames is not None else preset_train_frames
        pose_spec = novel_pose_frames if novel_pose_frames is not None else preset_pose_frames
        step = int(eval_frame_step) if eval_frame_step is not None else preset_step
        self.train_frame_ids = _frame_range(train_spec, self.num_frames_total, "train_frames")
        if split == "train":
            self.frame_ids, self.views = self.train_frame_ids, self.train_views
        elif split == "novel_view":
            self.frame_ids, self.views = self.train_frame_ids[::step], self.test_views
        else:
            if pose_spec is None:
                raise ValueError(
                    f"zju_mocap: split 'novel_pose' needs novel_pose_frames=[start, end, step] (or a protocol preset "
                    f"that knows sequence '{self.sequence}')"
                )
            self.frame_ids = _frame_range(pose_spec, self.num_frames_total, "novel_pose_frames")[::step]
            self.views = self.novel_pose_views

        # ---- poses (whole sequence: pose-refinement tables are num_frames_total long)
        self._load_params(body)

        # ---- every image and mask of the split: present, complete, one size (cameras: checked by ZjuSequence)
        self.src_width, self.src_height = self.seq.check_files(self.frame_ids, self.views, mask_dir)
        self.width = max(1, int(self.src_width / self.downscale))
        self.height = max(1, int(self.src_height / self.downscale))
        K = self.seq.cameras.K_splatrig()  # [C, 3, 3]
        K[:, 0] *= self.width / self.src_width
        K[:, 1] *= self.height / self.src_height
        self.cameras = Cameras(
            K=torch.tensor(K, dtype=torch.float32),
            world_to_cam=torch.tensor(self.seq.cameras.world_to_cam(), dtype=torch.float32),
            width=self.width,
            height=self.height,
        )
        self.bounds = self._compute_bounds(bounds_margin)

        # ---- caches
        self._lru = _LRU(int(cache_mb * 2**20))
        self._undistort_maps: dict[int, tuple[np.ndarray, np.ndarray] | None] = {}
        self._boundary_mem: dict[tuple[int, int], np.ndarray] = {}
        self.boundary_computations = 0
        self._boundary_dir: Path | None = None
        if boundary_cache == "disk":
            self._boundary_dir = self._pick_cache_dir(cache_dir)

    # ------------------------------------------------------------------------------------------------ loading
    def _load_params(self, body: str | None) -> None:
        used = set(self.frame_ids) | set(self.train_frame_ids)
        poses, rh, th, shapes = [], [], [], []
        body_key = None
        J = S = None
        missing = []
        last_exc: Exception | None = None
        for f in range(self.num_frames_total):
            try:
                path = self.seq.params_path(f)
            except FileNotFoundError as exc:
                if f in used:
                    raise
                missing.append(f)
                poses.append(None), rh.append(None), th.append(None), shapes.append(None)
                last_exc = exc
                continue
            p = self.seq.params(f)
            pose = np.asarray(p["poses"], dtype=np.float32).ravel()
            if pose.size % 3:
                raise ZjuFormatError(f"{path} (frame {f}): poses must hold J*3 values, found {pose.size}")
            if J is None:
                J = pose.size // 3
            elif pose.size != J * 3:
                raise ZjuFormatError(
                    f"{path} (frame {f}): poses hold {pose.size // 3} joints but frame {self.frame_ids[0]}'s hold {J}"
                )
            r = np.asarray(p["Rh"], dtype=np.float32).ravel()
            t = np.asarray(p["Th"], dtype=np.float32).ravel()
            s = np.asarray(p.get("shapes", np.zeros(10)), dtype=np.float32).ravel()
            S = s.size if S is None else S
            for name, arr in (("poses", pose), ("Rh", r), ("Th", t), ("shapes", s)):
                if not np.isfinite(arr).all():
                    idx = int(np.where(~np.isfinite(arr))[0][0])
                    where = f" (joint {idx // 3})" if name == "poses" else ""
                    raise ZjuFormatError(
                        f"{path} (frame {f}): '{name}' has a non-finite value {arr[idx]} at index {idx}{where}; "
                        f"expected finite numbers. Re-fit or drop this frame from the split."
                    )
            if r.size != 3 or t.size != 3:
                raise ZjuFormatError(f"{path} (frame {f}): Rh and Th must hold 3 values, found {r.size}, {t.size}")
            if body_key is None and "body" in p:
                body_key = str(p["body"])
            poses.append(pose.reshape(J, 3)), rh.append(r), th.append(t), shapes.append(s)
        if J is None:
            raise ZjuMissingFileError(f"zju_mocap: no params file found under {self.root}: {last_exc}")
        if missing:
            log.warning(
                "zju_mocap: %d frame(s) outside the split have no params (e.g. frame %d); using rest pose",
                len(missing),
                missing[0],
            )
        zeros = (np.zeros((J, 3), np.float32), np.zeros(3, np.float32), np.zeros(3, np.float32),
                 np.zeros(S, np.float32))  # fmt: skip
        for f in missing:
            poses[f], rh[f], th[f], shapes[f] = zeros
        self._poses = torch.tensor(np.stack(poses))  # [F, J, 3]
        self._betas = torch.tensor(np.stack(shapes))  # [F, S]
        from framework.geometry import axis_angle_to_rotmat

        roots = torch.eye(4).repeat(self.num_frames_total, 1, 1)  # [F, 4, 4]
        roots[:, :3, :3] = axis_angle_to_rotmat(torch.tensor(np.stack(rh), dtype=torch.float64)).float()
        roots[:, :3, 3] = torch.tensor(np.stack(th))
        self._roots = roots
        self.body_name = body or body_key or "smpl"

    def _compute_bounds(self, margin: float) -> torch.Tensor:
        if self.seq.vertices_dir is not None:
            lo = np.full(3, np.inf)
            hi = np.full(3, -np.inf)
            for f in self.frame_ids:
                v = self.seq.vertices(f)
                lo = np.minimum(lo, v.min(0))
                hi = np.maximum(hi, v.max(0))
        else:
            th = self._roots[self.frame_ids, :3, 3].numpy()
            lo, hi = th.min(0) - 1.2, th.max(0) + 1.2
        return torch.tensor(np.stack([lo - margin, hi + margin]), dtype=torch.float32)  # [2, 3]

    def _pick_cache_dir(self, cache_dir: str | None) -> Path:
        tag = f"boundary_{self.boundary_px}px_{self.width}x{self.height}_{self.mask_dir}"
        if cache_dir is not None:
            base = Path(cache_dir)
        else:
            base = self.root / ".splatrig_cache"
            try:
                base.mkdir(parents=True, exist_ok=True)
                probe = base / ".probe"
                probe.touch()
                probe.unlink()
            except OSError:  # read-only dataset: fall back to the project cache
                from framework.paths import cache_dir as project_cache

                base = project_cache() / "zju_boundary" / re.sub(r"[^A-Za-z0-9_.-]", "_", str(self.root.resolve()))
        out = base / tag
        out.mkdir(parents=True, exist_ok=True)
        return out

    # ------------------------------------------------------------------------------------------------ images
    def _undistort(self, view: int, img: np.ndarray) -> np.ndarray:
        """cv2.undistort(img, K, D) with the maps computed once per view (K kept as the new camera matrix)."""
        import cv2

        if view not in self._undistort_maps:
            D = self.seq.cameras.D[view]
            if not np.any(D):
                self._undistort_maps[view] = None
            else:
                K = self.seq.cameras.K[view]
                h, w = img.shape[:2]
                self._undistort_maps[view] = cv2.initUndistortRectifyMap(K, D, None, K, (w, h), cv2.CV_16SC2)
        maps = self._undistort_maps[view]
        if maps is None:
            return img
        return cv2.remap(img, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)

    def _resize(self, img: np.ndarray) -> np.ndarray:
        import cv2

        if img.shape[1] == self.width and img.shape[0] == self.height:
            return img
        return cv2.resize(img, (self.width, self.height), interpolation=cv2.INTER_AREA)

    def load_uint8(self, frame: int, view: int) -> tuple[np.ndarray, np.ndarray]:
        """Processed (undistorted, downscaled) image uint8 [H, W, 3] and mask uint8 [H, W] (0..255 coverage)."""
        key = (frame, view)
        hit = self._lru.get(key)
        if hit is not None:
            return hit  # type: ignore[return-value]
        img = self.seq.image(frame, view)
        if img.shape[:2] != (self.src_height, self.src_width):
            raise ZjuFormatError(
                f"{self.seq.image_path(frame, view)} (frame {frame}, view {view}): image is {img.shape[1]}x"
                f"{img.shape[0]} but the sequence's images are {self.src_width}x{self.src_height}"
            )
        mpath = self.seq.mask_path(frame, view, self.mask_dir)
        from framework.data.zju_format import read_mask_file

        m = read_mask_file(mpath)
        if m.shape != img.shape[:2]:
            raise ZjuFormatError(
                f"{mpath} (frame {frame}, view {view}): mask is {m.shape[1]}x{m.shape[0]} (WxH) but its image "
                f"{self.seq.image_path(frame, view).name} is {img.shape[1]}x{img.shape[0]}; masks must match their "
                f"images pixel for pixel"
            )
        if not m.any():
            raise ZjuFormatError(
                f"{mpath} (frame {frame}, view {view}): the mask is empty (no foreground pixel); every (frame, view) "
                f"of a split must show the subject. Fix the mask, or leave the frame out (train_frames) or the view "
                f"(train_views / test_views)"
            )
        img = self._resize(self._undistort(view, img))
        m = self._resize(self._undistort(view, m * np.uint8(255)))
        out = (np.ascontiguousarray(img), np.ascontiguousarray(m))
        self._lru.put(key, out)
        return out

    def boundary(self, frame: int, view: int, mask_u8: np.ndarray | None = None) -> np.ndarray:
        """float32 [H, W] M_b of (frame, view), computed once and cached."""
        key = (frame, view)
        packed = self._boundary_mem.get(key)
        disk = None if self._boundary_dir is None else self._boundary_dir / f"{frame:06d}_{view:03d}.npy"
        if packed is None and disk is not None and disk.exists():
            packed = np.load(disk)
            self._boundary_mem[key] = packed
        if packed is None:
            if mask_u8 is None:
                mask_u8 = self.load_uint8(frame, view)[1]
            b = boundary_mask(mask_u8 >= 128, self.boundary_px)
            self.boundary_computations += 1
            packed = np.packbits(b.astype(bool).ravel())
            self._boundary_mem[key] = packed
            if disk is not None:
                with atomic_path(disk) as tmp:
                    np.save(tmp, packed)
        n = self.width * self.height
        return np.unpackbits(packed, count=n).reshape(self.height, self.width).astype(np.float32)

    # ------------------------------------------------------------------------------------------------ interface
    def __len__(self) -> int:
        return len(self.frame_ids) * len(self.views)

    def sample(self, index: int) -> tuple[int, int]:
        """(frame, view) of item `index`: frames outer, views inner."""
        if not 0 <= index < len(self):
            raise IndexError(f"zju_mocap: index {index} out of range for {len(self)} samples")
        return self.frame_ids[index // len(self.views)], self.views[index % len(self.views)]

    def __getitem__(self, index: int) -> FrameBatch:
        frame, view = self.sample(index)
        img_u8, m_u8 = self.load_uint8(frame, view)
        image = torch.from_numpy(img_u8).float().div_(255.0)  # [H, W, 3]
        mask = torch.from_numpy(m_u8).float().div_(255.0)  # [H, W]
        if self.mask_background:
            image = image * mask[..., None] + self.background * (1.0 - mask[..., None])
        boundary = torch.from_numpy(self.boundary(frame, view, m_u8))
        return FrameBatch(
            image=image[None],
            mask=mask[None],
            boundary=boundary[None],
            cameras=self.cameras.index(view),
            frame=torch.tensor([frame], dtype=torch.long),
            pose=self._poses[frame][None].clone(),
            root=self._roots[frame][None].clone(),
            betas=self._betas[frame][None].clone(),
            view=torch.tensor([view], dtype=torch.long),
        )

    def poses(self) -> torch.Tensor:
        return self._poses.clone()  # [F, J, 3]

    def roots(self) -> torch.Tensor:
        """[num_frames_total, 4, 4] root transforms [[R(Rh), Th], [0, 1]]."""
        return self._roots.clone()

    def betas(self) -> torch.Tensor:
        """[num_frames_total, S] shape parameters as stored per frame."""
        return self._betas.clone()

    def vertices(self, frame: int) -> torch.Tensor:
        """[V, 3] stored posed world vertices of `frame` (for checks and previews)."""
        return torch.from_numpy(self.seq.vertices(frame))
