"""Rotation helpers shared by rasterizers, deformers, correctors and bodies (quaternions are wxyz)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from framework.guards import AXIS_ANGLE_TAYLOR_SQ, NORM_EPS


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


def _rotmat_quat_tables() -> tuple[Tensor, Tensor, Tensor]:
    """Constants of `rotmat_to_quat`: R's 9 entries (row-major) -> 10 values by one product, and per formula the 4 of
    them it uses.

    Values 0-3: 1 + (+-m00 +- m11 +- m22) = 4w^2, 4x^2, 4y^2, 4z^2 (with the offset); 4-6: m21 - m12 = 4wx,
    m02 - m20 = 4wy, m10 - m01 = 4wz; 7-9: m10 + m01 = 4xy, m02 + m20 = 4xz, m12 + m21 = 4yz. Formula k is the row
    4 q_k q of the outer product 4 q q^T."""
    mix = torch.zeros(9, 10, dtype=torch.float64)
    for col, signs in enumerate(((1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1))):
        for d, sign in zip((0, 4, 8), signs, strict=True):
            mix[d, col] = sign
    # m21 - m12, m02 - m20, m10 - m01, m10 + m01, m02 + m20, m12 + m21 (entry 3i + j is m_ij)
    for col, (a, b, sign) in enumerate(((7, 5, -1), (2, 6, -1), (3, 1, -1), (3, 1, 1), (2, 6, 1), (5, 7, 1)), start=4):
        mix[a, col], mix[b, col] = 1.0, float(sign)
    offset = torch.tensor([1.0] * 4 + [0.0] * 6, dtype=torch.float64)
    rows = torch.tensor([[0, 4, 5, 6], [4, 1, 7, 8], [5, 7, 2, 9], [6, 8, 9, 3]])
    return mix, offset, rows


_ROTMAT_QUAT_MIX, _ROTMAT_QUAT_OFFSET, _ROTMAT_QUAT_ROWS = _rotmat_quat_tables()  # [9, 10], [10], [4, 4]


def rotmat_to_quat(R: Tensor) -> Tensor:
    """[..., 3, 3] rotation -> [..., 4] wxyz with w >= 0.

    Of the four rows of 4 q q^T that R gives linearly, it takes the one with the largest diagonal entry 4 q_k^2 >= 1
    (the best-conditioned formula, as pytorch3d) and normalises it: no square root and no division by a small number,
    so values and gradients stay finite for every rotation, 180 degrees included. One product and one gather instead of
    sixteen stacked candidate entries: at 8k float32 rotations 0.8 against 1.6 ms forward and 2.0-3.1 against 6.4-8.4 ms
    forward+backward (2-core CPU VM, medians, old and new alternated); values and gradients equal the sixteen-entry
    form's to 1e-15 in float64."""
    flat = R.reshape(-1, 9)  # [M, 9]
    vals = torch.addmm(_ROTMAT_QUAT_OFFSET.to(flat), flat, _ROTMAT_QUAT_MIX.to(flat))  # [M, 10]
    best = vals[:, :4].argmax(dim=-1)  # [M]
    q = F.normalize(vals.gather(1, _ROTMAT_QUAT_ROWS.to(best.device)[best]), dim=-1)  # [M, 4] = +-q
    return torch.where(q[:, :1] < 0, -q, q).reshape(*R.shape[:-2], 4)


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
