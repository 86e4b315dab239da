"""Blend-weight field: the body's skinning weights extended from its surface to the whole canonical box.

Every grid node takes the weights of its closest point on the rest surface (closest triangle, barycentric
interpolation of the triangle's vertex weights, computed exactly by `framework.rig.closest_point`), so a Gaussian off
the skin moves with the nearest skin. The grid is computed once per (body, box, resolution), cached on disk under
`cache_dir()/weight_fields`, and sampled trilinearly with `grid_sample` (points outside the box clamp to its border),
then renormalised so the weights are a partition of unity. Memory: R^3 * J * 4 bytes (64^3 x 24 joints = 25 MB).
"""

from __future__ import annotations

import hashlib
import os

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from framework.guards import WEIGHT_SUM_MIN
from framework.paths import cache_dir
from framework.rig.closest_point import closest_points

_CACHE_VERSION = "1"


def _np(x) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, Tensor) else np.asarray(x)


def grid_points(bounds: np.ndarray, resolution: int) -> np.ndarray:
    """Node positions [R, R, R, 3] indexed [z, y, x] (grid_sample's D, H, W order), corners on the box."""
    axes = [np.linspace(bounds[0, i], bounds[1, i], resolution) for i in range(3)]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    return np.stack([x, y, z], axis=-1)


def surface_weights(vertices, faces, skin_weights, points) -> np.ndarray:
    """Weights [Q, J] of the closest surface point to each query [Q, 3] (barycentric blend of vertex weights)."""
    f = _np(faces).astype(np.int64)
    w = _np(skin_weights).astype(np.float64)
    face, bary, _ = closest_points(_np(vertices), f, _np(points))
    out = (bary[:, :, None] * w[f[face]]).sum(1)  # [Q, J]
    return out / np.clip(out.sum(1, keepdims=True), WEIGHT_SUM_MIN, None)


def _cache_key(vertices, faces, skin_weights, bounds: np.ndarray, resolution: int) -> str:
    h = hashlib.sha1(_CACHE_VERSION.encode())
    for a in (_np(vertices).astype(np.float32), _np(faces).astype(np.int64), _np(skin_weights).astype(np.float32),
              bounds.astype(np.float32)):  # fmt: skip
        h.update(np.ascontiguousarray(a).tobytes())
        h.update(str(a.shape).encode())
    h.update(str(resolution).encode())
    return h.hexdigest()[:20]


def build_weight_grid(vertices, faces, skin_weights, bounds, resolution: int = 64, use_cache: bool = True) -> Tensor:
    """Volume [J, R, R, R] (float32, indexed [j, z, y, x]) of surface weights over `bounds` [2, 3]; disk-cached."""
    b = _np(bounds).astype(np.float64).reshape(2, 3)
    if resolution < 2:
        raise ValueError(f"weight field: grid_resolution must be >= 2, got {resolution}.")
    if not np.all(b[1] > b[0]):
        raise ValueError(f"weight field: bounds must be [min, max] with max > min on every axis, got {b.tolist()}.")
    path = cache_dir() / "weight_fields" / f"{_cache_key(vertices, faces, skin_weights, b, resolution)}.pt"
    if use_cache and path.exists():
        return torch.load(path, weights_only=True)
    pts = grid_points(b, resolution).reshape(-1, 3)
    w = surface_weights(vertices, faces, skin_weights, pts)  # [R^3, J]
    vol = torch.from_numpy(w.T.reshape(-1, resolution, resolution, resolution).astype(np.float32)).contiguous()
    if use_cache:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".tmp{os.getpid()}")
        torch.save(vol, tmp)
        os.replace(tmp, path)
    return vol


class WeightField(nn.Module):
    """Trilinear lookup of a precomputed weight volume; differentiable in the query points."""

    def __init__(self, volume: Tensor, bounds: Tensor) -> None:
        super().__init__()
        # Not saved in checkpoints: `bind` rebuilds it (from the disk cache) before a checkpoint is loaded.
        self.register_buffer("volume", volume.float()[None].contiguous(), persistent=False)  # [1, J, D, H, W]
        self.register_buffer("bounds", torch.as_tensor(bounds, dtype=torch.float32).reshape(2, 3), persistent=False)

    @classmethod
    def from_body(cls, body, bounds, resolution: int = 64, use_cache: bool = True) -> WeightField:
        for attr in ("rest_vertices", "faces", "skin_weights"):
            if getattr(body, attr, None) is None:
                raise ValueError(f"weight field: body {type(body).__name__} has no `{attr}`; LBS needs one.")
        vol = build_weight_grid(body.rest_vertices, body.faces, body.skin_weights, bounds, resolution, use_cache)
        return cls(vol, torch.as_tensor(_np(bounds), dtype=torch.float32))

    @property
    def num_joints(self) -> int:
        return int(self.volume.shape[1])

    def sample(self, points: Tensor) -> Tensor:
        """points [..., 3] canonical -> weights [..., J], non-negative, rows summing to 1."""
        shape = points.shape[:-1]
        lo, hi = self.bounds[0].to(points), self.bounds[1].to(points)
        g = (2.0 * (points.reshape(-1, 3) - lo) / (hi - lo) - 1.0).to(self.volume.dtype)  # [M, 3] (x, y, z)
        out = F.grid_sample(
            self.volume, g[None, None, None], mode="bilinear", padding_mode="border", align_corners=True
        )  # fmt: skip  [1, J, 1, 1, M]
        w = out[0, :, 0, 0].transpose(0, 1).clamp_min(0.0)  # [M, J]
        w = w / w.sum(-1, keepdim=True).clamp_min(WEIGHT_SUM_MIN)
        return w.to(points.dtype).reshape(*shape, -1)

    forward = sample
