"""Tensor dataclasses passed between components.

Shapes are written as comments; `C` cameras, `N` Gaussians, `J` joints, `K = (sh_degree + 1) ** 2` SH coefficients.
Conventions: world-to-camera matrices are OpenCV (x right, y down, z forward); quaternions are wxyz and need not be
normalised; pixel (row i, column j) has its centre at image coordinates (j + 0.5, i + 0.5).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import torch
from torch import Tensor


def num_sh_coeffs(degree: int) -> int:
    """Number of real SH coefficients up to and including `degree`."""
    return (degree + 1) ** 2


@dataclass
class Gaussians:
    """Gaussian parameters in their raw (unactivated) form, as they are optimised.

    Canonical Gaussians live in the rest pose; a deformer returns posed ones of the same type.
    """

    means: Tensor  # [N, 3] world (or canonical) positions
    quats: Tensor  # [N, 4] wxyz, unnormalised
    log_scales: Tensor  # [N, 3]
    opacity_logits: Tensor  # [N]
    sh: Tensor  # [N, K, 3]
    latents: Tensor | None = None  # [N, 9] learnable appearance codes
    skin_weights: Tensor | None = None  # [N, J] baked blend weights (None while a weight field supplies them)

    @property
    def num(self) -> int:
        return self.means.shape[0]

    @property
    def scales(self) -> Tensor:
        return torch.exp(self.log_scales)  # [N, 3]

    @property
    def opacities(self) -> Tensor:
        return torch.sigmoid(self.opacity_logits)  # [N]

    def replace(self, **changes: Tensor | None) -> Gaussians:
        return replace(self, **changes)

    def index(self, idx: Tensor) -> Gaussians:
        """A subset of Gaussians (boolean mask or index tensor along N)."""
        out = {}
        for f in fields(self):
            v = getattr(self, f.name)
            out[f.name] = None if v is None else v[idx]
        return Gaussians(**out)


@dataclass
class Cameras:
    """A batch of pinhole cameras sharing one image size."""

    K: Tensor  # [C, 3, 3] intrinsics in pixels
    world_to_cam: Tensor  # [C, 4, 4] OpenCV convention
    width: int
    height: int

    @property
    def num(self) -> int:
        return self.K.shape[0]

    @property
    def device(self) -> torch.device:
        return self.K.device

    def to(self, device: torch.device | str, dtype: torch.dtype | None = None, non_blocking: bool = False) -> Cameras:
        K, w2c = (t.to(device, dtype, non_blocking=non_blocking) for t in (self.K, self.world_to_cam))
        return Cameras(K, w2c, self.width, self.height)

    def pin_memory(self) -> Cameras:
        """In page-locked host memory (a DataLoader with `pin_memory=True` calls this), so the copy to a GPU can run
        without the host waiting for it."""
        return Cameras(self.K.pin_memory(), self.world_to_cam.pin_memory(), self.width, self.height)

    def centers(self) -> Tensor:
        """Camera centres in world coordinates, [C, 3]."""
        R = self.world_to_cam[:, :3, :3]
        t = self.world_to_cam[:, :3, 3]
        return -(R.transpose(1, 2) @ t.unsqueeze(-1)).squeeze(-1)

    def index(self, idx: int | slice | Tensor) -> Cameras:
        if isinstance(idx, int):
            idx = slice(idx, idx + 1)
        return Cameras(self.K[idx], self.world_to_cam[idx], self.width, self.height)

    def resized(self, width: int, height: int) -> Cameras:
        """The same cameras with images of width x height: the intrinsics' x row scales by width / self.width and the
        y row by height / self.height (pixel i spans [i, i + 1], so a point's pixel coordinates scale exactly)."""
        K = self.K.clone()
        K[:, 0] *= width / self.width
        K[:, 1] *= height / self.height
        return Cameras(K, self.world_to_cam, width, height)


@dataclass
class RenderOutput:
    """What every rasterizer backend returns."""

    rgb: Tensor  # [C, H, W, 3] composited colour over the background
    alpha: Tensor  # [C, H, W, 1] accumulated opacity (= a render with white colours on black)
    depth: Tensor | None  # [C, H, W, 1] accumulated camera-space z, sum_i w_i z_i (divide by alpha for expected depth)
    means2d: Tensor  # [C, N, 2] projected centres in pixels; `.grad` is filled after backward (densification)
    radii: Tensor  # [C, N] integer pixel radius of the 3-sigma footprint, 0 where culled


@dataclass
class BlendWeights:
    """What each Gaussian adds to the images, as composited: its blending weights w = T * alpha over every (pixel,
    camera) pair where it contributes (after the alpha cull and early termination), summarised per Gaussian.
    Pruning ranks by them (`framework.compaction.pruning`)."""

    max: Tensor  # [N] the largest w
    square_sum: Tensor  # [N] sum of w^2 (float64: sums over many frames)
    pairs: Tensor  # [N] how many pairs have w > 0 (float64 counts)

    @classmethod
    def zeros(
        cls, n: int, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32
    ) -> BlendWeights:
        z = torch.zeros(n, dtype=torch.float64, device=device)
        return cls(torch.zeros(n, dtype=dtype, device=device), z, z.clone())

    def add(self, other: BlendWeights) -> BlendWeights:
        """The summary of both sets of images (of the same Gaussians)."""
        return BlendWeights(
            torch.maximum(self.max, other.max.to(self.max.dtype)),
            self.square_sum + other.square_sum,
            self.pairs + other.pairs,
        )

    @property
    def mean_square(self) -> Tensor:
        """[N] the mean w^2 over the pairs a Gaussian costs the rasterizer (0 where it has none): the image change its
        removal makes per pixel it covers, squared (float32)."""
        return (self.square_sum / self.pairs.clamp_min(1.0)).float()


@dataclass
class FrameBatch:
    """One training/evaluation sample: images of one frame from one or more cameras (B views)."""

    image: Tensor  # [B, H, W, 3] float in [0, 1]
    mask: Tensor  # [B, H, W] float in [0, 1], foreground
    boundary: Tensor  # [B, H, W] float, 0 within n pixels of the silhouette, 1 elsewhere (M_b)
    cameras: Cameras  # C = B
    frame: Tensor  # [B] long, frame index into the sequence (pose refinement looks it up)
    pose: Tensor | None = None  # [B, J, 3] axis-angle joint rotations of the body model (None for static scenes)
    root: Tensor | None = None  # [B, 4, 4] root transform applied after the body model (EasyMocap R(Rh), Th)
    betas: Tensor | None = None  # [B, S] shape parameters where the body model uses them
    view: Tensor | None = None  # [B] long, camera index in the rig

    def to(self, device: torch.device | str, non_blocking: bool = False) -> FrameBatch:
        """On `device`. `non_blocking` from page-locked memory (`pin_memory`) lets the host queue the step's kernels
        while the copy runs (training on a GPU); from ordinary memory the copy waits for the device either way."""
        return self._map(
            lambda x: x.to(device, non_blocking=non_blocking), self.cameras.to(device, non_blocking=non_blocking)
        )

    def pin_memory(self) -> FrameBatch:
        """In page-locked host memory (a DataLoader with `pin_memory=True` calls this in its pinning thread)."""
        return self._map(lambda x: x.pin_memory(), self.cameras.pin_memory())

    def _map(self, move, cameras: Cameras) -> FrameBatch:
        def mv(x):
            return None if x is None else move(x)

        return FrameBatch(
            image=move(self.image),
            mask=move(self.mask),
            boundary=move(self.boundary),
            cameras=cameras,
            frame=move(self.frame),
            pose=mv(self.pose),
            root=mv(self.root),
            betas=mv(self.betas),
            view=mv(self.view),
        )
