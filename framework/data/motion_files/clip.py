"""A motion ready to drive an avatar (poses in the avatar body's convention) and its frame-rate resampling."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np


@dataclass
class Motion:
    """Per-frame poses of the avatar's own body, as a dataset stores them."""

    poses: np.ndarray  # [F, J, 3] float32 axis-angle, the body's convention (framework.interfaces.body)
    roots: np.ndarray | None  # [F, 4, 4] root transforms (world = root @ body), None: the body's own frame
    fps: float | None  # frames per second; None when the source does not say
    source: str  # where it came from, for messages and file names

    @property
    def num_frames(self) -> int:
        return int(self.poses.shape[0])

    def head(self, n: int | None) -> Motion:
        """The first `n` frames (all when n is None)."""
        if n is None:
            return self
        return replace(self, poses=self.poses[:n], roots=None if self.roots is None else self.roots[:n])


def _slerp_rotvecs(rotvecs: np.ndarray, t_in: np.ndarray, t_out: np.ndarray) -> np.ndarray:
    """[F, 3] axis-angles keyed at t_in -> [F', 3] at t_out, spherical-linear between neighbouring keys."""
    from scipy.spatial.transform import Rotation, Slerp

    return Slerp(t_in, Rotation.from_rotvec(rotvecs))(t_out).as_rotvec()


def resample(motion: Motion, fps: float) -> Motion:
    """The motion at `fps` frames per second over the same duration ((F - 1) / fps_in seconds).

    Joint and root rotations are interpolated by slerp between the two nearest source frames, root translations
    linearly; output frame i samples time i / fps, so frame 0 is the source's frame 0. A motion without a known
    frame rate, or already at `fps`, is returned unchanged (with `fps` filled in when it was unknown).
    """
    if fps <= 0:
        raise ValueError(f"resample: fps must be positive, got {fps}.")
    if motion.fps is None or abs(motion.fps - fps) < 1e-9 * fps or motion.num_frames < 2:
        return replace(motion, fps=float(fps) if motion.fps is None else motion.fps)
    n_in = motion.num_frames
    t_in = np.arange(n_in) / motion.fps
    duration = t_in[-1]
    n_out = int(np.floor(duration * fps + 1e-6)) + 1
    t_out = np.minimum(np.arange(n_out) / fps, duration)
    J = motion.poses.shape[1]
    poses = np.stack([_slerp_rotvecs(motion.poses[:, j], t_in, t_out) for j in range(J)], axis=1)  # [F', J, 3]
    roots = None
    if motion.roots is not None:
        from scipy.spatial.transform import Rotation

        rot = Rotation.from_rotvec(
            _slerp_rotvecs(Rotation.from_matrix(motion.roots[:, :3, :3]).as_rotvec(), t_in, t_out)
        ).as_matrix()
        roots = np.tile(np.eye(4), (n_out, 1, 1))
        roots[:, :3, :3] = rot
        for axis in range(3):
            roots[:, axis, 3] = np.interp(t_out, t_in, motion.roots[:, axis, 3])
        roots = roots.astype(np.float32)
    return Motion(poses.astype(np.float32), roots, float(fps), motion.source)
