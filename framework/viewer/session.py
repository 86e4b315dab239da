"""What the viewer shows and how it is rendered, independent of the web page: motions, the frame, hand-made joint
offsets, the corrector / weight-residual / backend switches, and one render per request.

Kept apart from viser so that tests can drive it directly and the page stays a thin layer of widgets.
"""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from framework.animation.frames import render_rgb, to_uint8
from framework.animation.sources import SPLITS, body_rig, load_motion
from framework.data.motion_files import Motion
from framework.errors import SplatrigError
from framework.registry import RASTERIZERS
from framework.types import Cameras


@dataclass
class FrameStats:
    seconds: float  # wall time of the last render (pose + rasterise)
    num_gaussians: int
    width: int
    height: int
    served: int  # renders so far


class ViewerSession:
    """State of one viewer; every public method is safe to call from viser's callback threads."""

    def __init__(self, module, dm, motion_file: str | None = None, fps: float = 25.0, backend: str | None = None):
        self.module = module.eval()
        self.avatar = module.avatar
        self.dm = dm
        self.fps = float(fps)
        self.lock = threading.RLock()
        self.sh_degree = int(module.sh_degree(module.trained_steps()))
        self.motions: dict[str, tuple[Motion, list[int]]] = {}
        if self.avatar.body is not None:
            for split in ("train", "novel_pose"):
                try:
                    self.motions[split] = load_motion(module, dm, split)
                except (SplatrigError, ValueError) as exc:
                    print(f"[splatrig] viewer: motion '{split}' unavailable: {exc}", file=sys.stderr)
            if motion_file:
                self.add_motion_file(motion_file)
        self.motion_name = next(iter(self.motions), None)
        self.frame = 0
        num_joints = 0 if self.avatar.body is None else self.avatar.body.num_joints
        self.offsets = np.zeros((num_joints, 3))  # [J, 3] axis-angle added on top of the motion (world axes)
        self._rasterizers = {type(self.avatar.rasterizer).registry_name: self.avatar.rasterizer}
        self.backend = type(self.avatar.rasterizer).registry_name
        self._prepare_weights()
        if backend and backend != self.backend:
            self.set_backend(backend)
        self.served = 0
        self.last = FrameStats(0.0, self.avatar.gaussians.num, 0, 0, 0)

    # ------------------------------------------------------------------------------------------------ options
    @property
    def joint_names(self) -> list[str]:
        return [] if self.avatar.body is None else list(self.avatar.body.joint_names)

    @property
    def default_joint(self) -> str | None:
        """The joint the pose sliders start on: the left shoulder when the body names one (the most telling)."""
        if not self.joint_names:
            return None
        rig = body_rig(self.avatar.body)
        k = rig.index.get("shoulder.L", 1) if rig is not None else min(1, len(self.joint_names) - 1)
        return self.joint_names[k]

    @property
    def has_corrector(self) -> bool:
        return self.avatar.body is not None and self.avatar.corrector.registry_name != "none"

    @property
    def has_residual(self) -> bool:
        return self._grid_weights is not None

    @staticmethod
    def available_backends() -> list[str]:
        return [e.name for e in RASTERIZERS if e.unavailable_reason() is None]

    def _prepare_weights(self) -> None:
        """Bake the final blend weights (the real-time path) and, where the deformer's stage-2 part (F_dw) changes
        them, the weights without it too, so the F_dw switch swaps one tensor instead of evaluating it every frame."""
        self._full_weights = self._grid_weights = None
        deformer = self.avatar.deformer
        params = self.avatar.gaussians.params
        if "skin_weights" not in params and not self.module.bake_weights():
            return  # no body, or a deformer with nothing to bake
        self._full_weights = params["skin_weights"].data.clone()
        was = deformer.enabled
        deformer.enabled = False
        canonical = self.avatar.gaussians.gaussians().replace(skin_weights=None)
        grid = deformer.bake(canonical)
        deformer.enabled = was
        if grid is not None and not torch.equal(grid, self._full_weights):
            self._grid_weights = grid.detach().clone()

    def _changed(self) -> None:
        # the avatar caches the posed Gaussians of the last pose; leaving training mode again clears that cache
        self.avatar.train(False)

    def set_corrector(self, on: bool) -> None:
        with self.lock:
            self.avatar.corrector.enabled = bool(on)
            self._changed()

    def set_residual(self, on: bool) -> None:
        with self.lock:
            if self._grid_weights is None:
                return
            weights = self._full_weights if on else self._grid_weights
            self.avatar.gaussians.params["skin_weights"].data = weights.clone()
            self._changed()

    def set_backend(self, name: str) -> None:
        with self.lock:
            if name not in self._rasterizers:
                entry = RASTERIZERS.entry(name)
                reason = entry.unavailable_reason()
                if reason is not None:
                    raise SplatrigError(f"rasterizer '{name}' cannot run here: {reason}.")
                self._rasterizers[name] = RASTERIZERS.build(name)
            self.avatar.rasterizer = self._rasterizers[name]
            self.backend = name

    # ------------------------------------------------------------------------------------------------ motion
    def add_motion_file(self, path: str) -> str:
        """Load a motion file (resampled to the viewer's fps) and return its name in `motions`."""
        with self.lock:
            motion, frames = load_motion(self.module, self.dm, str(path), self.fps)
            name = str(path) if str(path) not in SPLITS else f"file:{path}"
            self.motions[name] = (motion, frames)
            return name

    def select(self, motion_name: str | None = None, frame: int | None = None) -> None:
        with self.lock:
            if motion_name is not None:
                if motion_name not in self.motions:
                    raise SplatrigError(f"viewer: unknown motion '{motion_name}'; loaded: {list(self.motions)}.")
                self.motion_name = motion_name
            if frame is not None:
                self.frame = int(frame)
            self.frame = min(max(self.frame, 0), self.num_frames - 1)

    @property
    def num_frames(self) -> int:
        return 1 if self.motion_name is None else self.motions[self.motion_name][0].num_frames

    def set_offset(self, joint: int, degrees_xyz) -> None:
        """Rotate joint `joint` by the axis-angle `degrees_xyz` (degrees; its parent's axes) on top of the motion."""
        with self.lock:
            self.offsets[int(joint)] = np.radians(np.asarray(degrees_xyz, dtype=np.float64))

    def reset_offsets(self) -> None:
        with self.lock:
            self.offsets[:] = 0.0

    def current_pose(self) -> tuple[torch.Tensor | None, torch.Tensor | None, int]:
        """(pose [J, 3], root [4, 4] or None, frame id) now shown: the motion's frame with each joint's offset
        applied after it, in the parent's world-aligned rest axes (R = R(offset) R(motion))."""
        if self.avatar.body is None:
            return None, None, -1
        if self.motion_name is None:
            base, root, frame_id = np.zeros_like(self.offsets), None, -1
        else:
            motion, frames = self.motions[self.motion_name]
            base = motion.poses[self.frame].astype(np.float64)
            root = None if motion.roots is None else torch.as_tensor(motion.roots[self.frame])
            frame_id = frames[self.frame]
        pose = (Rotation.from_rotvec(self.offsets) * Rotation.from_rotvec(base)).as_rotvec()
        return torch.as_tensor(pose, dtype=torch.float32), root, frame_id

    # ------------------------------------------------------------------------------------------------ render
    def render(self, cameras: Cameras) -> np.ndarray:
        """uint8 [H, W, 3] of the current state seen by `cameras` (one camera)."""
        with self.lock:
            pose, root, frame_id = self.current_pose()
            start = time.perf_counter()
            rgb = render_rgb(self.module, cameras, pose, root, frame_id)[0]
            image = to_uint8(rgb)
            self.served += 1
            self.last = FrameStats(
                time.perf_counter() - start, self.avatar.gaussians.num, cameras.width, cameras.height, self.served
            )
            return image
