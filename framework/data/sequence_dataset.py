"""What every dataset read from a calibrated multi-view sequence on disk shares (the ZJU-MoCap layout, EasyMocap's
output): views and frames per split, per-frame body parameters, undistortion, downscaling, masks, boundary masks and
their caches. A reader (`MultiViewSequence`) says where things are; `SequenceDataset` turns them into FrameBatches.

What a sample is: one (frame, view) pair of the split, as a FrameBatch with B = 1.
- Image: decoded on access (never all images as float32), undistorted with cv2's undistort maps (D applied, K kept,
  as Neural Body / Animatable NeRF / EasyMocap do), downscaled with INTER_AREA, composited over a black (or white)
  background with the mask (Animatable NeRF's `mask_bkgd`), float32 in [0, 1]. An optional LRU cache keeps processed
  uint8 images.
- Mask: foreground as the reader defines it, undistorted and area-downscaled like the image (fractional at the edge).
- Boundary M_b: 0 within n output pixels of the silhouette (mask >= 0.5), computed once per (frame, view) and cached in
  memory (bit-packed) and optionally on disk. n = `boundary_px`, or with `boundary_ref_side` set, `boundary_px` at that
  image side scaled to the output's shorter side (`framework.data.boundary.scaled_half_width`).
- Cameras: K converted from OpenCV's pixel convention (centres at integers) to ours (centres at j + 0.5): cx += 0.5,
  cy += 0.5; then for a downscale to W' x H', K'[0] = K[0] * W'/W and K'[1] = K[1] * H'/H. In the half-pixel convention
  a pure scaling of image coordinates is exact for area resampling (output pixel j' covers input [s j', s j' + s),
  centred at s (j' + 0.5)); the same formula in OpenCV's convention would be cx' = (cx + 0.5) / s - 0.5.
  world_to_cam = [[R, T], [0, 1]] with T in metres.
- Body: pose = params["poses"] reshaped [J, 3] (the global-orient slot kept as stored), root = [[R(Rh), Th], [0, 1]]
  (EasyMocap: world = R(Rh) M(pose, shapes) + Th about the origin), betas = params["shapes"].
- bounds: the world-space box of the stored posed vertices over the split's frames, grown by `bounds_margin` metres
  on every side. The body model is not known here, so this is not a canonical box; without stored vertices it falls
  back to the Th positions grown by 1.2 m.
"""

from __future__ import annotations

import logging
import re
from collections import OrderedDict
from pathlib import Path
from typing import Any, ClassVar, Protocol

import numpy as np
import torch

from framework.atomic import atomic_path
from framework.data.boundary import boundary_mask, scaled_half_width
from framework.data.options import SequenceOptions
from framework.data.zju.layout import ZjuFormatError, ZjuMissingFileError, check_complete
from framework.data.zju.reader import ZjuCameras
from framework.geometry import axis_angle_to_rotmat
from framework.interfaces import MultiViewDataset
from framework.types import Cameras, FrameBatch

log = logging.getLogger(__name__)

SPLITS = ("train", "novel_view", "novel_pose")


class MultiViewSequence(Protocol):
    """A lazy reader of one sequence: what `SequenceDataset` asks of a layout (ZjuSequence, EasyMocapSequence)."""

    root: Path
    cameras: ZjuCameras  # the whole rig, as stored (OpenCV K, distortion, world-to-camera R and T)
    camera_names: list[str]  # one per view, for messages and reports
    vertices_dir: Any  # None when the sequence stores no posed vertices

    @property
    def num_frames(self) -> int: ...
    @property
    def num_views(self) -> int: ...
    def image_path(self, frame: int, view: int) -> Path: ...
    def image(self, frame: int, view: int) -> np.ndarray: ...  # uint8 [H, W, 3] RGB, as stored (distorted)
    def mask_path(self, frame: int, view: int, mask_dir: str = "auto") -> Path: ...
    def read_mask(self, path: Path) -> np.ndarray: ...  # uint8 [H, W] in {0, 1}
    def params_path(self, frame: int) -> Path: ...  # raises FileNotFoundError when the frame has none
    def params(self, frame: int) -> dict: ...  # poses [1, J*3], Rh [1, 3], Th [1, 3], shapes [1, S], optional body
    def vertices(self, frame: int) -> np.ndarray: ...  # [V, 3] float32 posed world vertices


def frame_range(spec: Any, num_frames: int, what: str) -> list[int]:
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


def check_files(seq: MultiViewSequence, frames: list[int], views: list[int], mask_dir: str = "auto") -> tuple[int, int]:
    """Open every image and mask of (frames x views) far enough to know it is there, complete, and of one size with
    its mask and the other images (headers only: ~1 ms a pair); returns (width, height). Errors name the file, the
    frame and the view."""
    from PIL import Image, UnidentifiedImageError

    def size(path: Path, what: str, frame: int, view: int) -> tuple[int, int]:
        try:
            with Image.open(path) as im:
                wh = im.size
        except (UnidentifiedImageError, OSError) as exc:
            raise ZjuFormatError(
                f"{what} {path} (frame {frame}, view {view}) cannot be read as an image "
                f"({type(exc).__name__}); export it again"
            ) from None
        check_complete(path, what)
        return wh

    expected: tuple[int, int] | None = None
    first = Path()
    for f in frames:
        for v in views:
            image = seq.image_path(f, v)
            if not image.exists():
                seq.image(f, v)  # raises the reader's missing-image message
            wh = size(image, "image file", f, v)
            if expected is None:
                expected, first = wh, image
            elif wh != expected:
                raise ZjuFormatError(
                    f"{image} (frame {f}, view {v}): image is {wh[0]}x{wh[1]} but {first.name} of frame {frames[0]}, "
                    f"view {views[0]} is {expected[0]}x{expected[1]}; every image of a sequence must have the same size"
                )
            mask = seq.mask_path(f, v, mask_dir)
            mwh = size(mask, "mask file", f, v)
            if mwh != wh:
                raise ZjuFormatError(
                    f"{mask} (frame {f}, view {v}): mask is {mwh[0]}x{mwh[1]} (WxH) but its image {image.name} is "
                    f"{wh[0]}x{wh[1]}; masks must match their images pixel for pixel"
                )
    assert expected is not None
    return expected


class LRU:
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


class SequenceDataset(MultiViewDataset):
    """One split of a sequence read by `seq`; subclasses open their layout, resolve its presets into `options` and
    call `__init__`.

    `options.train_views` / `test_views` / `novel_pose_views` are view indices (train views default to every view,
    test views to every view not trained on, view 0 when that leaves none, like Animatable NeRF; novel-pose views to
    the test views). Frames are `frame_range` specs; evaluation splits take every `eval_frame_step`-th frame of theirs.
    """

    #: the dataclasses a subclass's config keys (beyond its own parameters) are dealt out to
    config_schemas: ClassVar[tuple[type, ...]] = (SequenceOptions,)

    def __init__(self, seq: MultiViewSequence, *, split: str, options: SequenceOptions) -> None:
        super().__init__()
        name = self.label
        if split not in SPLITS:
            raise ValueError(f"{name}: split must be one of {SPLITS}, got '{split}'")
        self.seq = seq
        self.root = seq.root
        self.split = split
        self.options = options
        self.mask_dir = options.mask_dir
        self.background = 1.0 if options.white_background else 0.0
        self.num_frames_total = seq.num_frames
        C = seq.num_views

        # ---- views and frames of the split
        views_all = list(range(C))
        self.train_views = list(options.train_views) if options.train_views is not None else views_all
        complement = [v for v in views_all if v not in self.train_views]
        self.test_views = list(options.test_views) if options.test_views is not None else (complement or [0])
        self.novel_pose_views = (
            list(options.novel_pose_views) if options.novel_pose_views is not None else self.test_views
        )
        for what, vs in (
            ("train_views", self.train_views),
            ("test_views", self.test_views),
            ("novel_pose_views", self.novel_pose_views),
        ):
            bad = [v for v in vs if not (isinstance(v, int) and 0 <= v < C)]
            if bad or not vs:
                raise ValueError(f"{name}: {what}={vs} must be non-empty view indices in 0..{C - 1} ({self.root})")
        self.train_frame_ids = frame_range(options.train_frames, self.num_frames_total, "train_frames")
        step = options.eval_frame_step or 1
        if split == "train":
            self.frame_ids, self.views = self.train_frame_ids, self.train_views
        elif split == "novel_view":
            self.frame_ids, self.views = self.train_frame_ids[::step], self.test_views
        else:
            if options.novel_pose_frames is None:
                raise ValueError(f"{name}: split 'novel_pose' needs novel_pose_frames=[start, end, step]")
            self.frame_ids = frame_range(options.novel_pose_frames, self.num_frames_total, "novel_pose_frames")[::step]
            self.views = self.novel_pose_views

        # ---- poses (whole sequence: pose-refinement tables are num_frames_total long)
        self._load_params(options.body)

        # ---- every image and mask of the split: present, complete, one size (the reader checks the cameras)
        self.src_width, self.src_height = check_files(seq, self.frame_ids, self.views, self.mask_dir)
        self.width = max(1, int(self.src_width / options.downscale))
        self.height = max(1, int(self.src_height / options.downscale))
        side = min(self.width, self.height)
        self.boundary_px = scaled_half_width(options.boundary_px, side, options.boundary_ref_side)
        K = seq.cameras.K_splatrig()  # [C, 3, 3]
        K[:, 0] *= self.width / self.src_width
        K[:, 1] *= self.height / self.src_height
        self.cameras = Cameras(
            K=torch.tensor(K, dtype=torch.float32),
            world_to_cam=torch.tensor(seq.cameras.world_to_cam(), dtype=torch.float32),
            width=self.width,
            height=self.height,
        )
        self.bounds = self._compute_bounds(options.bounds_margin)

        # ---- caches
        self._lru = LRU(int(options.cache_mb * 2**20))
        self._undistort_maps: dict[int, tuple[np.ndarray, np.ndarray] | None] = {}
        self._boundary_mem: dict[tuple[int, int], np.ndarray] = {}
        self.boundary_computations = 0
        self._boundary_dir: Path | None = None
        if options.boundary_cache == "disk":
            self._boundary_dir = self._pick_cache_dir(options.cache_dir)

    @property
    def label(self) -> str:
        """The dataset's registry name, for messages."""
        return self.registry_name or type(self).__name__

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
            for key, arr in (("poses", pose), ("Rh", r), ("Th", t), ("shapes", s)):
                if not np.isfinite(arr).all():
                    idx = int(np.where(~np.isfinite(arr))[0][0])
                    where = f" (joint {idx // 3})" if key == "poses" else ""
                    raise ZjuFormatError(
                        f"{path} (frame {f}): '{key}' has a non-finite value {arr[idx]} at index {idx}{where}; "
                        f"expected finite numbers. Re-fit or drop this frame from the split."
                    )
            if r.size != 3 or t.size != 3:
                raise ZjuFormatError(f"{path} (frame {f}): Rh and Th must hold 3 values, found {r.size}, {t.size}")
            if body_key is None and "body" in p:
                body_key = str(p["body"])
            poses.append(pose.reshape(J, 3)), rh.append(r), th.append(t), shapes.append(s)
        if J is None:
            raise ZjuMissingFileError(f"{self.label}: no params file found under {self.root}: {last_exc}")
        if missing:
            log.warning(
                "%s: %d frame(s) outside the split have no params (e.g. frame %d); using rest pose",
                self.label,
                len(missing),
                missing[0],
            )
        zeros = (
            np.zeros((J, 3), np.float32),
            np.zeros(3, np.float32),
            np.zeros(3, np.float32),
            np.zeros(S, np.float32),
        )
        for f in missing:
            poses[f], rh[f], th[f], shapes[f] = zeros
        self._poses = torch.tensor(np.stack(poses))  # [F, J, 3]
        self._betas = torch.tensor(np.stack(shapes))  # [F, S]
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
        m = self.seq.read_mask(mpath)
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
            raise IndexError(f"{self.label}: index {index} out of range for {len(self)} samples")
        return self.frame_ids[index // len(self.views)], self.views[index % len(self.views)]

    def __getitem__(self, index: int) -> FrameBatch:
        frame, view = self.sample(index)
        img_u8, m_u8 = self.load_uint8(frame, view)
        image = torch.from_numpy(img_u8).float().div_(255.0)  # [H, W, 3]
        mask = torch.from_numpy(m_u8).float().div_(255.0)  # [H, W]
        if self.options.mask_background:
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

    def fitted_betas(self) -> torch.Tensor:
        """[S] mean of the training frames' stored shapes (EasyMocap fits one shape for the whole sequence)."""
        return self._betas[self.train_frame_ids].mean(0)

    def has_vertices(self) -> bool:
        """Whether the sequence stores posed world vertices (else they come from a body model and the poses)."""
        return self.seq.vertices_dir is not None

    def vertices(self, frame: int) -> torch.Tensor:
        """[V, 3] stored posed world vertices of `frame` (for checks and previews)."""
        return torch.from_numpy(self.seq.vertices(frame))

    def body_box(self, frame: int) -> np.ndarray | None:
        from framework.evaluation.body_box import frame_box

        return frame_box(self.seq.vertices(frame)) if self.has_vertices() else None
