"""Rotation helpers shared by rasterizers, deformers, correctors and bodies (quaternions are wxyz)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from framework.guards import AXIS_ANGLE_TAYLOR_SQ, NORM_EPS, ROTMAT_QUAT_DENOM_MIN, ROTMAT_QUAT_SQ_MIN


def _normalize_with_norm(q: Tensor, eps: float = NORM_EPS) -> tuple[Tensor, Tensor]:
    """(q / |q| [..., 4], |q| [..., 1]); a quaternion below eps maps to the identity rather than NaN."""
    norm = q.norm(dim=-1, keepdim=True)
    identity = torch.zeros_like(q)
    identity[..., 0] = 1.0
    return torch.where(norm > eps, q / norm.clamp_min(eps), identity), norm


def quat_normalize(q: Tensor, eps: float = NORM_EPS) -> Tensor:
    """Normalise [..., 4]; a zero quaternion maps to the identity rather than NaN."""
    return _normalize_with_norm(q, eps)[0]


def _rotmat_of_unit(q: Tensor) -> Tensor:
    """[..., 4] unit wxyz -> [..., 3, 3] (the quadratic form; no normalisation)."""
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(*q.shape[:-1], 3, 3)  # fmt: skip


class _QuatToRotmat(torch.autograd.Function):
    """quat_to_rotmat with a closed-form backward, because every rasterizer projection and LBS step runs it on all
    Gaussians. Autograd through its ~40 elementwise ops made forward+backward 3.5 ms at 8k quaternions and 7.4 ms at
    30k on CPU (interleaved medians); this takes 2.7 and 5.7 ms. tests/test_geometry.py checks it against an
    independent (Rodrigues) construction and against finite differences."""

    @staticmethod
    def forward(ctx, q: Tensor) -> Tensor:  # type: ignore[override]
        qn, norm = _normalize_with_norm(q)  # [..., 4], [..., 1]
        ctx.save_for_backward(qn, norm)
        return _rotmat_of_unit(qn)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g: Tensor) -> Tensor:  # type: ignore[override]
        qn, norm = ctx.saved_tensors
        w, x, y, z = qn.unbind(-1)
        g00, g01, g02, g10, g11, g12, g20, g21, g22 = g.flatten(-2).unbind(-1)
        s01, s02, s12 = g01 + g10, g02 + g20, g12 + g21  # symmetric parts
        a01, a02, a12 = g10 - g01, g02 - g20, g21 - g12  # antisymmetric parts
        g_unit = 2 * torch.stack(
            [
                z * a01 + y * a02 + x * a12,
                y * s01 + z * s02 + w * a12 - 2 * x * (g11 + g22),
                x * s01 + w * a02 + z * s12 - 2 * y * (g00 + g22),
                w * a01 + x * s02 + y * s12 - 2 * z * (g00 + g11),
            ],
            dim=-1,
        )  # [..., 4] dL/d(unit quaternion)
        # through q / |q|: remove the radial part; a quaternion below NORM_EPS maps to the constant identity
        g_q = (g_unit - qn * (qn * g_unit).sum(-1, keepdim=True)) / norm.clamp_min(NORM_EPS)
        return torch.where(norm > NORM_EPS, g_q, torch.zeros_like(g_q))


def quat_to_rotmat(q: Tensor) -> Tensor:
    """[..., 4] wxyz (any norm) -> [..., 3, 3]."""
    return _QuatToRotmat.apply(q)


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product a * b of [..., 4] wxyz quaternions (rotation b first, then a)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def rotmat_to_quat(R: Tensor) -> Tensor:
    """[..., 3, 3] rotation -> [..., 4] wxyz with w >= 0; picks the best-conditioned of four formulas (as pytorch3d),
    so values and gradients stay finite for every rotation, 180 degrees included."""
    m00, m01, m02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    m10, m11, m12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    m20, m21, m22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    q_abs = torch.sqrt(
        torch.stack(
            [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], dim=-1
        ).clamp_min(ROTMAT_QUAT_SQ_MIN)
    )  # [..., 4] = 2 * |(w, x, y, z)|
    candidates = torch.stack(
        [
            torch.stack([q_abs[..., 0] ** 2, m21 - m12, m02 - m20, m10 - m01], dim=-1),
            torch.stack([m21 - m12, q_abs[..., 1] ** 2, m10 + m01, m02 + m20], dim=-1),
            torch.stack([m02 - m20, m10 + m01, q_abs[..., 2] ** 2, m12 + m21], dim=-1),
            torch.stack([m10 - m01, m20 + m02, m21 + m12, q_abs[..., 3] ** 2], dim=-1),
        ],
        dim=-2,
    ) / (2 * q_abs[..., None].clamp_min(ROTMAT_QUAT_DENOM_MIN))  # [..., 4 (formula), 4]
    best = q_abs.argmax(dim=-1)  # [...]
    q = candidates.gather(-2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    q = F.normalize(q, dim=-1)
    return torch.where(q[..., :1] < 0, -q, q)


def axis_angle_to_rotmat(aa: Tensor) -> Tensor:
    """[..., 3] axis-angle -> [..., 3, 3] (Rodrigues), with finite values and gradients at zero angle."""
    theta2 = (aa * aa).sum(-1, keepdim=True)  # [..., 1]
    small = theta2 < AXIS_ANGLE_TAYLOR_SQ
    theta2_safe = torch.where(small, torch.ones_like(theta2), theta2)
    theta = torch.sqrt(theta2_safe)
    # sin(t)/t and (1-cos(t))/t^2 with Taylor expansions near zero
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta2_safe)
    x, y, z = aa.unbind(-1)
    zero = torch.zeros_like(x)
    Kx = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(*aa.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=aa.dtype, device=aa.device).expand_as(Kx)
    return eye + a[..., None] * Kx + b[..., None] * (Kx @ Kx)
