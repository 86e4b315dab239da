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

from framework.geometry import quat_to_rotmat
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
) -> Projection:
    """Project N Gaussians into C pinhole cameras (see the module docstring for the rules)."""
    R = world_to_cam[:, :3, :3]  # [C, 3, 3]
    t = world_to_cam[:, :3, 3]  # [C, 3]
    p = torch.einsum("cij,nj->cni", R, means) + t[:, None, :]  # [C, N, 3]
    x, y, z = p.unbind(-1)  # [C, N]
    in_depth = (z > near) & (z < far)
    z_safe = torch.where(in_depth, z, torch.ones_like(z))  # keeps culled entries finite

    fx, fy = K[:, 0, 0, None], K[:, 1, 1, None]  # [C, 1]
    cx, cy = K[:, 0, 2, None], K[:, 1, 2, None]
    u = x / z_safe
    v = y / z_safe
    means2d = torch.stack([fx * u + cx, fy * v + cy], dim=-1)  # [C, N, 2]

    # Jacobian at the mean with x/z, y/z clamped to the widened field of view (3DGS/gsplat).
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    u_lim = (-(cx / fx + FOV_MARGIN * tan_fovx), (width - cx) / fx + FOV_MARGIN * tan_fovx)  # ([C, 1], [C, 1])
    v_lim = (-(cy / fy + FOV_MARGIN * tan_fovy), (height - cy) / fy + FOV_MARGIN * tan_fovy)
    u_c = torch.minimum(torch.maximum(u, u_lim[0]), u_lim[1])
    v_c = torch.minimum(torch.maximum(v, v_lim[0]), v_lim[1])
    rz = 1.0 / z_safe
    # T = J W R S with J = [[fx/z, 0, -fx u/z], [0, fy/z, -fy v/z]] written out (tiny batched matmuls are slow on CPU)
    RS = quat_to_rotmat(quats) * scales.unsqueeze(-2)  # [N, 3, 3]
    WRS = torch.einsum("cij,njk->cnik", R, RS)  # [C, N, 3, 3]
    r0, r1, r2 = WRS.unbind(-2)  # [C, N, 3] rows
    T0 = (fx * rz).unsqueeze(-1) * r0 - (fx * u_c * rz).unsqueeze(-1) * r2
    T1 = (fy * rz).unsqueeze(-1) * r1 - (fy * v_c * rz).unsqueeze(-1) * r2
    cxx = (T0 * T0).sum(-1) + eps2d  # dilated Sigma2d = T T^T + eps2d I
    cxy = (T0 * T1).sum(-1)
    cyy = (T1 * T1).sum(-1) + eps2d
    # det = cxx cyy - cxy^2 without the cancellation: |T0|^2 |T1|^2 - (T0.T1)^2 = |T0 x T1|^2 (Lagrange's identity),
    # so a needle-thin Gaussian (anisotropy 1e6) keeps its determinant's digits in float32 instead of losing them all.
    # (the cross product written out per component: 2.3x faster than torch.linalg.cross forward+backward at 30k rows
    # on CPU, tools/bench_rasterizers.py's scene)
    (a0, a1, a2), (b0, b1, b2) = T0.unbind(-1), T1.unbind(-1)
    cross_sq = (a1 * b2 - a2 * b1).square() + (a2 * b0 - a0 * b2).square() + (a0 * b1 - a1 * b0).square()  # [C, N]
    det = cross_sq + eps2d * (cxx + cyy - eps2d)
    ok_det = det > 0
    det_safe = torch.where(ok_det, det, torch.ones_like(det))
    conics = torch.stack([cyy / det_safe, -cxy / det_safe, cxx / det_safe], dim=-1)  # [C, N, 3]
    cov2d = torch.stack([cxx, cxy, cyy], dim=-1)

    with torch.no_grad():
        op = opacities.detach().to(z.dtype).expand_as(z)  # [C, N]
        visible = op >= ALPHA_MIN
        extend = torch.sqrt(2.0 * torch.log((op / ALPHA_MIN).clamp_min(1.0))).clamp_max(EXTEND_MAX)
        half = torch.stack(
            [extend * cxx.detach().clamp_min(0).sqrt(), extend * cyy.detach().clamp_min(0).sqrt()], dim=-1
        )  # [C, N, 2]
        half = torch.nan_to_num(half, nan=0.0, posinf=float(2**30), neginf=0.0).clamp_max(float(2**30))
        rad = torch.ceil(half)  # per-axis integer radii, as gsplat culls with them
        m2 = means2d.detach()
        inside = (
            (m2[..., 0] + rad[..., 0] > 0)
            & (m2[..., 0] - rad[..., 0] < width)
            & (m2[..., 1] + rad[..., 1] > 0)
            & (m2[..., 1] - rad[..., 1] < height)
        )
        finite = torch.isfinite(m2).all(-1) & torch.isfinite(cov2d.detach()).all(-1)
        valid = in_depth & ok_det & visible & inside & finite & (rad.amax(-1) > 0)
        radii = torch.where(valid, rad.amax(-1), torch.zeros_like(rad[..., 0])).to(torch.int32)
        half = torch.where(valid[..., None], half, torch.zeros_like(half))
    return Projection(
        means2d=means2d, conics=conics, cov2d=cov2d, depths=z, half_extents=half, radii=radii, valid=valid
    )
