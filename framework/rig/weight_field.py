"""Blend-weight field: the body's skinning weights extended from its surface to the whole canonical box.

Every grid node takes the weights of its closest point on the rest surface (closest triangle, barycentric
interpolation of the triangle's vertex weights, computed exactly by `framework.rig.closest_point`), so a Gaussian off
the skin moves with the nearest skin. The grid is computed once per (body, box, resolution), cached on disk under
`cache_dir()/weight_fields`, and sampled trilinearly (points outside the box clamp to its border, as `grid_sample`'s
`padding_mode="border"`), then renormalised so the weights are a partition of unity. Memory: R^3 * J * 4 bytes
(64^3 x 24 joints = 25 MB).

Sampling reads a channels-last copy of the volume ([R^3, J], each row one node's J weights, contiguous) with one
`embedding_bag` call: each point is four bags of its 8 corner rows, weighted by the trilinear weights and by their
derivatives along x, y and z, so the forward returns the value and keeps the three derivatives, and the backward is one
[3, J] x [J] product per point. Nothing of size [M, 8, J] is written. In `tools/bench_train.py` this shortens the
stage-1 backward against a gather of the corner rows and three lerps (which itself is faster than `F.grid_sample`: that
reads the channels-first volume with J strided loads per corner; it computes the same values to float rounding,
tested). A volume that is a partition of
unity (every grid `build_weight_grid` writes) needs no clamp or renormalisation per lookup: trilinear samples are convex
combinations of its rows.
"""

from __future__ import annotations

import hashlib

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from framework.atomic import atomic_path
from framework.guards import WEIGHT_FIELD_NAN_NODE, WEIGHT_PARTITION_TOL, WEIGHT_SUM_MIN
from framework.paths import cache_dir
from framework.rig.closest_point import closest_points

_CACHE_VERSION = "2"  # 2: closest triangles from libigl (ties on shared edges may pick the other face)


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
    for a in (
        _np(vertices).astype(np.float32),
        _np(faces).astype(np.int64),
        _np(skin_weights).astype(np.float32),
        bounds.astype(np.float32),
    ):
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
        with atomic_path(path) as tmp:
            torch.save(vol, tmp)
    return vol


def _corner_affine_factors() -> tuple[Tensor, Tensor]:
    """(a, b) [3, 32]: column (bag, dz, dy, dx) of the 4 bags x 8 corners, per axis, is a + b * frac_axis.

    Bag 0 is the trilinear value, weights (1 - f) or f per axis; bag 1 + i is its derivative along axis i (x, y, z),
    which replaces that axis's factor by -1 (lower corner) or +1 (upper corner)."""
    a, b = torch.zeros(3, 32), torch.zeros(3, 32)
    cols = [(bag, (dx, dy, dz)) for bag in range(4) for dz in (0, 1) for dy in (0, 1) for dx in (0, 1)]
    for j, (bag, bits) in enumerate(cols):
        for axis, bit in enumerate(bits):
            if bag == axis + 1:
                a[axis, j] = 1.0 if bit else -1.0
            else:
                a[axis, j], b[axis, j] = (0.0, 1.0) if bit else (1.0, -1.0)
    return a, b


class _Trilinear(torch.autograd.Function):
    """Trilinear lookup as weighted bags of corner rows; differentiable in the in-cell coordinates only (the table is
    data). The forward evaluates four bags per point in one `embedding_bag`: the value and its three derivatives along
    the cell axes, so the backward is one small batched dot product per point."""

    @staticmethod
    def forward(ctx, table: Tensor, idx: Tensor, frac: Tensor, factors: Tensor) -> Tensor:  # type: ignore[override]
        """table [R^3, J], idx [M, 8] corner rows in (dz, dy, dx) order, frac [M, 3], factors [2, 3, 32] -> [M, J]."""
        M = frac.shape[0]
        a, b = factors
        f = [torch.addcmul(a[i], frac[:, i : i + 1], b[i]) for i in range(3)]  # [M, 32] per axis
        bags = f[0].mul_(f[1]).mul_(f[2]).view(M * 4, 8)  # [4M, 8] corner weights, bag-major per point
        rows = idx.unsqueeze(1).expand(M, 4, 8).reshape(M * 4, 8)
        out = F.embedding_bag(rows, table, per_sample_weights=bags, mode="sum")  # [4M, J]
        out = out.view(M, 4, table.shape[1])  # [M, 4, J]
        ctx.save_for_backward(out)
        return out[:, 0]

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Tensor) -> tuple[None, None, Tensor, None]:  # type: ignore[override]
        (out,) = ctx.saved_tensors
        return None, None, torch.bmm(out[:, 1:], grad.unsqueeze(-1)).squeeze(-1), None  # [M, 3]


def _trilinear_value(table: Tensor, idx: Tensor, frac: Tensor, factors: Tensor) -> Tensor:
    """The value bag alone (no gradient needed): [M, J]."""
    a, b = factors[:, :, :8]
    f = [torch.addcmul(a[i], frac[:, i : i + 1], b[i]) for i in range(3)]  # [M, 8] per axis
    return F.embedding_bag(idx, table, per_sample_weights=f[0].mul_(f[1]).mul_(f[2]), mode="sum")


class WeightField(nn.Module):
    """Trilinear lookup of a precomputed weight volume; differentiable in the query points."""

    def __init__(self, volume: Tensor, bounds: Tensor) -> None:
        super().__init__()
        # Not saved in checkpoints: `bind` rebuilds it (from the disk cache) before a checkpoint is loaded.
        self.partition_of_unity = bool(
            (volume >= 0).all() and (volume.double().sum(0) - 1.0).abs().max() <= WEIGHT_PARTITION_TOL
        )
        if self.partition_of_unity:  # exact rows, so every convex combination of them sums to 1 (to rounding)
            volume = volume.double() / volume.double().sum(0, keepdim=True)
        volume = volume.float()
        self.resolution = tuple(int(r) for r in volume.shape[1:])  # (D, H, W)
        if min(self.resolution) < 2:
            raise ValueError(f"weight field: volume needs >= 2 nodes per axis, got shape {tuple(volume.shape)}.")
        self.register_buffer(
            "table", volume.permute(1, 2, 3, 0).reshape(-1, volume.shape[0]).contiguous(), persistent=False
        )  # [D*H*W, J], row (z * H + y) * W + x
        self.register_buffer("bounds", torch.as_tensor(bounds, dtype=torch.float32).reshape(2, 3), persistent=False)
        D, H, W = self.resolution
        corners = [(z * H + y) * W + x for z in (0, 1) for y in (0, 1) for x in (0, 1)]  # [dz, dy, dx] order
        self.register_buffer("corner_offsets", torch.tensor(corners), persistent=False)  # [8]
        self.register_buffer("factors", torch.stack(_corner_affine_factors()), persistent=False)  # [2, 3, 32]
        self.register_buffer("max_index", torch.tensor([W - 1, H - 1, D - 1], dtype=torch.float32), persistent=False)

    @classmethod
    def from_body(cls, body, bounds, resolution: int = 64, use_cache: bool = True) -> WeightField:
        vol = build_weight_grid(body.rest_vertices, body.faces, body.skin_weights, bounds, resolution, use_cache)
        return cls(vol, torch.as_tensor(_np(bounds), dtype=torch.float32))

    @property
    def num_joints(self) -> int:
        return int(self.table.shape[1])

    @property
    def volume(self) -> Tensor:
        """The weights as a [1, J, D, H, W] volume (grid_sample's layout), a view of the table."""
        return self.table.t().reshape(1, -1, *self.resolution)

    def sample(self, points: Tensor) -> Tensor:
        """points [..., 3] canonical -> weights [..., J], non-negative, rows summing to 1.

        Differentiable in the points; zero gradient outside the box (border clamp), as grid_sample's border mode.
        """
        shape = points.shape[:-1]
        lo, hi = self.bounds[0].to(points), self.bounds[1].to(points)
        dtype = self.table.dtype
        u = ((points.reshape(-1, 3) - lo) / (hi - lo)).to(dtype) * self.max_index  # [M, 3] node units (x, y, z)
        # border clamp with zero gradient on and beyond the faces (as grid_sample's clip_coordinates); NaN -> a node
        outside = torch.minimum(u.detach().nan_to_num(nan=WEIGHT_FIELD_NAN_NODE).clamp_min(0.0), self.max_index)
        u = torch.where((u > 0) & (u < self.max_index), u, outside)
        i0 = torch.minimum(u.detach().floor(), self.max_index - 1)  # lower corner, so that frac is in [0, 1]
        frac = u - i0  # [M, 3]
        i0 = i0.long()
        _, H, W = self.resolution
        base = (i0[:, 2] * H + i0[:, 1]) * W + i0[:, 0]  # [M]
        idx = base[:, None] + self.corner_offsets  # [M, 8]
        factors = self.factors.to(dtype)
        if torch.is_grad_enabled() and frac.requires_grad:
            w = _Trilinear.apply(self.table, idx, frac, factors)  # [M, J]
        else:
            w = _trilinear_value(self.table, idx, frac, factors)
        if not self.partition_of_unity:  # else w is a convex combination of rows that already are
            w = w.clamp_min(0.0)
            w = w / w.sum(-1, keepdim=True).clamp_min(WEIGHT_SUM_MIN)
        return w.to(points.dtype).reshape(*shape, self.num_joints)

    forward = sample
