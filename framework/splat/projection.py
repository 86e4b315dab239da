"""EWA projection of 3D Gaussians to screen space, as fixed by `framework.interfaces.rasterizer`.

A pure function of its tensors, so every backend (and the densifier's bookkeeping) can share it: gsplat-compatible
field-of-view-clamped Jacobian, 0.3 px^2 low-pass dilation, near/far culling, conic, and the opacity-aware screen box
(half extents extend * sqrt(Sigma2d_xx), extend * sqrt(Sigma2d_yy) with extend = min(3.33, sqrt(2 ln(255 opacity))),
the smallest box holding every pixel where alpha >= 1/255).
Culled entries keep finite values (and finite gradients, which are zero) so no NaN leaks into a backward pass.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from framework.device_constants import values_on
from framework.execution import COMPILED, Execution
from framework.geometry import quat_to_rotmat_entry_major
from framework.splat.contract import ALPHA_MIN, EPS2D, FAR_PLANE, NEAR_PLANE

EXTEND_MAX = 3.33
FOV_MARGIN = 0.3


@dataclass
class Projection:
    """Screen-space Gaussians for C cameras; entries where `valid` is False are culled."""

    means2d: Tensor  # [C, N, 2] pixel coordinates of the projected centres (differentiable)
    conics: Tensor  # [C, N, 3] (a, b, c) of Sigma2d^-1 = [[a, b], [b, c]] (differentiable)
    cov2d: Tensor  # [C, N, 3] (xx, xy, yy) of the dilated Sigma2d (differentiable)
    depths: Tensor  # [C, N] camera-space z (differentiable)
    half_extents: Tensor  # [C, N, 2] float half width/height of the alpha >= 1/255 box in pixels (no grad)
    radii: Tensor  # [C, N] int32 ceil(max half extent); 0 where culled
    valid: Tensor  # [C, N] bool


def project_gaussians(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    K: Tensor,  # [C, 3, 3]
    world_to_cam: Tensor,  # [C, 4, 4]
    width: int,
    height: int,
    near: float = NEAR_PLANE,
    far: float = FAR_PLANE,
    eps2d: float = EPS2D,
    execution: Execution = COMPILED,
) -> Projection:
    """Project N Gaussians into C pinhole cameras (see the module docstring for the rules); `execution` picks the
    rotation helpers' torch form (`framework.geometry.few_kernels`).

    Component-major inside: camera-space x, y, z and the rows of T = J W R S are [C, N] and [C, 3, N] tensors (one
    batched product each), so every elementwise step reads contiguous rows, and the per-camera constants come from one
    small [C, 8] table (faster than the entry-major form on a CPU: docs/results/speed.md)."""
    C, N = K.shape[0], means.shape[0]
    R = world_to_cam[:, :3, :3]  # [C, 3, 3]
    x, y, z = torch.baddbmm(world_to_cam[:, :3, 3:], R, means.t().expand(C, 3, N)).unbind(1)  # [C, N] each
    in_depth = (z > near) & (z < far)
    rz = torch.where(in_depth, z, 1.0).reciprocal()  # [C, N]; 1 on culled entries keeps them finite

    # Per camera: fx, fy, cx, cy and the limits of x/z, y/z in the field of view widened by FOV_MARGIN (3DGS/gsplat)
    f, c = K.diagonal(dim1=1, dim2=2)[:, :2], K[:, :2, 2]  # [C, 2] each (views: no index tensors to copy)
    size = values_on((float(width), float(height)), K.device, K.dtype)  # [2], made once per size and device
    lo = (c + (0.5 * FOV_MARGIN) * size).div(f).neg()  # [C, 2]
    hi = ((1.0 + 0.5 * FOV_MARGIN) * size - c).div(f)
    fx, fy, cx, cy, u_lo, v_lo, u_hi, v_hi = torch.cat([f, c, lo, hi], dim=1).unsqueeze(-1).unbind(1)  # [C, 1] each
    u, v = x * rz, y * rz
    means2d = torch.stack([torch.addcmul(cx, fx, u), torch.addcmul(cy, fy, v)], dim=-1)  # [C, N, 2]

    # T = J W R S with J = [[fx/z, 0, -fx u/z], [0, fy/z, -fy v/z]] at x/z, y/z clamped to the widened field of view:
    # T_0 = fx/z (row 0 - u_c row 2 of W R S), T_1 = fy/z (row 1 - v_c row 2)
    R_gauss = quat_to_rotmat_entry_major(quats.t(), execution).view(3, 3, N)  # [3, 3, N]
    RS = R_gauss * scales.t().unsqueeze(0)  # [3, 3, N]: (R S)_kj per row
    W0, W1, W2 = torch.matmul(R, RS.view(3, 3 * N)).reshape(C, 3, 3, N).unbind(1)  # rows of W R S, [C, 3, N]
    T0 = (W0 - torch.clamp(u, u_lo, u_hi).unsqueeze(1) * W2) * (fx * rz).unsqueeze(1)  # [C, 3, N]
    T1 = (W1 - torch.clamp(v, v_lo, v_hi).unsqueeze(1) * W2) * (fy * rz).unsqueeze(1)
    cxx = (T0 * T0).sum(1) + eps2d  # [C, N]: dilated Sigma2d = T T^T + eps2d I
    cxy = (T0 * T1).sum(1)
    cyy = (T1 * T1).sum(1) + eps2d
    # det = cxx cyy - cxy^2 without the cancellation: |T0|^2 |T1|^2 - (T0.T1)^2 = |T0 x T1|^2 (Lagrange's identity),
    # so a needle-thin Gaussian (anisotropy 1e6) keeps its determinant's digits in float32 instead of losing them all.
    # (the cross product written out per component: 2.3x faster than torch.linalg.cross forward+backward at 30k rows
    # on CPU, tools/bench_rasterizers.py's scene)
    (a0, a1, a2), (b0, b1, b2) = T0.unbind(1), T1.unbind(1)
    cross_sq = (a1 * b2 - a2 * b1).square() + (a2 * b0 - a0 * b2).square() + (a0 * b1 - a1 * b0).square()  # [C, N]
    det = cross_sq + eps2d * (cxx + cyy - eps2d)
    ok_det = det > 0
    inv = torch.where(ok_det, det, 1.0).reciprocal()
    conics = torch.stack([cyy * inv, -cxy * inv, cxx * inv], dim=-1)  # [C, N, 3]
    cov2d = torch.stack([cxx, cxy, cyy], dim=-1)

    with torch.no_grad():
        op = opacities.detach().to(z.dtype)  # [N]
        extend = torch.log((op / ALPHA_MIN).clamp_min(1.0)).mul_(2.0).sqrt_().clamp_max_(EXTEND_MAX)  # [N]
        half = cov2d.detach()[..., ::2].clamp_min(0).sqrt_().mul_(extend.unsqueeze(-1))  # [C, N, 2]
        half = torch.nan_to_num(half, nan=0.0, posinf=float(2**30), neginf=0.0).clamp_max_(float(2**30))
        rad = torch.ceil(half)  # per-axis integer radii, as gsplat culls with them
        m2 = means2d.detach()
        inside = ((m2 + rad > 0) & (m2 - rad < size)).all(-1)  # the box overlaps the image
        finite = torch.isfinite(torch.cat([m2, cov2d.detach()], dim=-1)).all(-1)
        radii = rad.amax(-1)
        valid = in_depth & ok_det & (op >= ALPHA_MIN) & inside & finite & (radii > 0)
        radii = (radii * valid).to(torch.int32)
        half = half * valid.unsqueeze(-1)
    return Projection(
        means2d=means2d, conics=conics, cov2d=cov2d, depths=z, half_extents=half, radii=radii, valid=valid
    )
