"""Rotation helpers shared by rasterizers, deformers, correctors and bodies (quaternions are wxyz)."""

from __future__ import annotations

import torch
from torch import Tensor

from framework.device_constants import constant_on
from framework.execution import COMPILED, Execution
from framework.guards import AXIS_ANGLE_TAYLOR_SQ, NORM_EPS


def _normalize_with_norm(q: Tensor, eps: float = NORM_EPS, dim: int = -1) -> tuple[Tensor, Tensor]:
    """(q / |q|, |q| with `dim` kept) of quaternions along `dim`; one below eps maps to the identity rather than NaN.

    |q| as the root of the clamped sum of squares, an order of magnitude faster than `Tensor.norm` over a 4-wide
    dimension in either layout; the clamp at eps^2 (below the threshold) keeps the root's slope finite at zero, where
    the gradient is then exactly zero."""
    norm = q.square().sum(dim, keepdim=True).clamp_min(eps * eps).sqrt()
    identity = constant_on(IDENTITY_QUAT, q.device, q.dtype)  # [4], broadcast (no zeros_like, select and fill)
    identity = identity if dim in (-1, q.dim() - 1) else identity.view(4, *([1] * (q.dim() - 1 - (dim % q.dim()))))
    return torch.where(norm > eps, q / norm.clamp_min(eps), identity), norm


IDENTITY_QUAT = torch.tensor([1.0, 0.0, 0.0, 0.0])  # wxyz; read-only, moved to a device by `constant_on`


def quat_normalize(q: Tensor, eps: float = NORM_EPS, dim: int = -1, execution: Execution = COMPILED) -> Tensor:
    """Normalise quaternions along `dim` ([..., 4]; dim=0 for [4, N]); a zero one maps to the identity, not NaN."""
    if q.requires_grad and few_kernels(q, execution):
        return _QuatNormalize.apply(q, eps, dim)
    return _normalize_with_norm(q, eps, dim)[0]


class _QuatNormalize(torch.autograd.Function):
    """`quat_normalize` with its closed-form backward, g_q = (g - q (q . g)) / |q| (zero below eps), on accelerators:
    10 backward operators a call where autograd through the forward issues 22 (a few calls a training step). The CPU
    keeps autograd's, which its training path has always used."""

    @staticmethod
    def forward(ctx, q: Tensor, eps: float, dim: int) -> Tensor:  # type: ignore[override]
        qn, norm = _normalize_with_norm(q, eps, dim)
        ctx.save_for_backward(qn, norm)
        ctx.eps, ctx.dim = eps, dim
        return qn

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g: Tensor) -> tuple[Tensor, None, None]:  # type: ignore[override]
        qn, norm = ctx.saved_tensors
        g_q = (g - qn * (qn * g).sum(ctx.dim, keepdim=True)) / norm.clamp_min(ctx.eps)
        return torch.where(norm > ctx.eps, g_q, torch.zeros_like(g_q)), None, None


def _rotmat_entries(w: Tensor, x: Tensor, y: Tensor, z: Tensor) -> list[Tensor]:
    """The nine entries (row-major) of the rotation of the unit quaternion wxyz (the quadratic form)."""
    return [
        1 - 2 * (y * y + z * z),
        2 * (x * y - w * z),
        2 * (x * z + w * y),
        2 * (x * y + w * z),
        1 - 2 * (x * x + z * z),
        2 * (y * z - w * x),
        2 * (x * z - w * y),
        2 * (y * z + w * x),
        1 - 2 * (x * x + y * y),
    ]


def _product_table(terms: list[list[tuple[int, int, float]]]) -> tuple[Tensor, Tensor]:
    """Bilinear forms out_e = sum_t c_et u_i v_j with four terms each, as a gather index into the flattened outer
    product u v^T ([16]: 4i + j) and the coefficients, both [4 * len(terms)] (a missing term has coefficient 0)."""
    index, coef = [], []
    for row in terms:
        padded = row + [(0, 0, 0.0)] * (4 - len(row))
        index += [4 * i + j for i, j, _ in padded]
        coef += [c for _, _, c in padded]
    return torch.tensor(index), torch.tensor(coef, dtype=torch.float64)


def _rotation_tables() -> tuple[tuple[Tensor, Tensor], tuple[Tensor, Tensor]]:
    """The rotation of a unit quaternion as homogeneous quadratic forms (R00 = w^2 + x^2 - y^2 - z^2,
    R01 = 2 (xy - wz), ..., row-major), and the Hamilton product a * b (out_i = signed sums of a_j b_k)."""
    w, x, y, z = range(4)
    rotation = _product_table(
        [
            [(w, w, 1), (x, x, 1), (y, y, -1), (z, z, -1)],
            [(x, y, 2), (w, z, -2)],
            [(x, z, 2), (w, y, 2)],
            [(x, y, 2), (w, z, 2)],
            [(w, w, 1), (x, x, -1), (y, y, 1), (z, z, -1)],
            [(y, z, 2), (w, x, -2)],
            [(x, z, 2), (w, y, -2)],
            [(y, z, 2), (w, x, 2)],
            [(w, w, 1), (x, x, -1), (y, y, -1), (z, z, 1)],
        ]
    )
    hamilton = _product_table(
        [
            [(w, w, 1), (x, x, -1), (y, y, -1), (z, z, -1)],
            [(w, x, 1), (x, w, 1), (y, z, 1), (z, y, -1)],
            [(w, y, 1), (x, z, -1), (y, w, 1), (z, x, 1)],
            [(w, z, 1), (x, y, 1), (y, x, -1), (z, w, 1)],
        ]
    )
    return rotation, hamilton


(_ROTMAT_INDEX, _ROTMAT_COEF), (_HAMILTON_INDEX, _HAMILTON_COEF) = _rotation_tables()  # [36], [36]; [16], [16]


def _bilinear(a: Tensor, b: Tensor, dim: int, index: Tensor, coef: Tensor) -> Tensor:
    """The four-term bilinear forms of `_product_table` of 4-vectors a, b along `dim` (0 or -1), stacked along `dim`.

    Why: four kernels each way (outer product, gather, scale, sum) where the entry-by-entry formulas issue one kernel
    per product and sum, ~25-40 forward and as many backward. A GPU pays a launch for every kernel, and a training step
    is made of many small ones (tools/count_syncs.py), so the accelerators take this form; a CPU runs the
    entry-by-entry one faster. Element-wise products and sums only, so no matrix product rounds to TF32."""
    index, coef = constant_on(index, a.device), constant_on(coef, a.device, a.dtype)
    if dim == 0:  # [4, N] -> [len, N]
        outer = (a.unsqueeze(1) * b.unsqueeze(0)).flatten(0, 1)  # [16, N]
        terms = outer.index_select(0, index) * coef.unsqueeze(-1)  # [4 len, N]
        return terms.view(-1, 4, terms.shape[-1]).sum(1)
    outer = (a.unsqueeze(-1) * b.unsqueeze(-2)).flatten(-2)  # [..., 16]
    terms = outer.index_select(-1, index) * coef  # [..., 4 len]
    return terms.unflatten(-1, (-1, 4)).sum(-1)


def few_kernels(t: Tensor, execution: Execution) -> bool:
    """Whether the rotation helpers take their few-kernel forms for t: every tensor `execution` does not compile (a
    GPU's; a CPU's under the torch execution, which runs the GPU's code). Each helper takes the model's execution as
    its last argument (default: compiled, the CPU's own forms on a CPU)."""
    return not execution.compiled(t)


class _QuatToRotmat(torch.autograd.Function):
    """quat_to_rotmat with a closed-form backward, because every rasterizer projection and LBS step runs it on all
    Gaussians, and autograd through its ~40 elementwise ops is slower (docs/results/speed.md). tests/test_geometry.py
    checks it against an independent (Rodrigues) construction and against finite differences.

    `dim` is where the four components sit: -1 for [..., 4] -> [..., 3, 3]; 0 for component-major [4, N] -> entry-major
    [9, N] (row 3i + j = entry (i, j)), the layout the projection and the LBS compute in."""

    @staticmethod
    def forward(ctx, q: Tensor, dim: int) -> Tensor:  # type: ignore[override]
        qn, norm = _normalize_with_norm(q, dim=dim)  # [..., 4], [..., 1] (or [4, N], [1, N])
        ctx.save_for_backward(qn, norm)
        ctx.dim = dim
        R = torch.stack(_rotmat_entries(*qn.unbind(dim)), dim=dim)
        return R if dim == 0 else R.reshape(*q.shape[:-1], 3, 3)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g: Tensor) -> tuple[Tensor, None]:  # type: ignore[override]
        qn, norm = ctx.saved_tensors
        dim = ctx.dim
        w, x, y, z = qn.unbind(dim)
        g00, g01, g02, g10, g11, g12, g20, g21, g22 = (g if dim == 0 else g.flatten(-2)).unbind(dim)
        s01, s02, s12 = g01 + g10, g02 + g20, g12 + g21  # symmetric parts
        a01, a02, a12 = g10 - g01, g02 - g20, g21 - g12  # antisymmetric parts
        g_unit = 2 * torch.stack(
            [
                z * a01 + y * a02 + x * a12,
                y * s01 + z * s02 + w * a12 - 2 * x * (g11 + g22),
                x * s01 + w * a02 + z * s12 - 2 * y * (g00 + g22),
                w * a01 + x * s02 + y * s12 - 2 * z * (g00 + g11),
            ],
            dim=dim,
        )  # dL/d(unit quaternion)
        # through q / |q|: remove the radial part; a quaternion below NORM_EPS maps to the constant identity
        g_q = (g_unit - qn * (qn * g_unit).sum(dim, keepdim=True)) / norm.clamp_min(NORM_EPS)
        return torch.where(norm > NORM_EPS, g_q, torch.zeros_like(g_q)), None


def quat_to_rotmat(q: Tensor, execution: Execution = COMPILED) -> Tensor:
    """[..., 4] wxyz (any norm) -> [..., 3, 3]."""
    if few_kernels(q, execution):
        unit = quat_normalize(q, execution=execution)
        return _bilinear(unit, unit, -1, _ROTMAT_INDEX, _ROTMAT_COEF).unflatten(-1, (3, 3))
    return _QuatToRotmat.apply(q, -1)


def quat_to_rotmat_entry_major(q: Tensor, execution: Execution = COMPILED) -> Tensor:
    """Component-major quaternions [4, N] wxyz (any norm; `quats.t()` of [N, 4] will do) -> entry-major rotations
    [9, N] (row 3i + j = entry (i, j)): every row contiguous for the vector math that follows."""
    if q.dim() != 2 or q.shape[0] != 4:
        raise ValueError(f"quat_to_rotmat_entry_major: expected [4, N], got shape {tuple(q.shape)}.")
    if few_kernels(q, execution):
        unit = quat_normalize(q, dim=0, execution=execution)
        return _bilinear(unit, unit, 0, _ROTMAT_INDEX, _ROTMAT_COEF)
    return _QuatToRotmat.apply(q, 0)


def products_3x3(X: Tensor, Y: Tensor, transpose_x: bool = False) -> Tensor:
    """Batched 3x3 products of entry-major [3, 3, N] matrices (entry (i, j) of matrix n at [i, j, n]): X Y, or X^T Y.

    One broadcast product and one sum over contiguous rows of N values, where [N, 3, 3] batches run N tiny matrix
    products: the layout of the LBS and polar decomposition's per-Gaussian math."""
    if transpose_x:
        return (X.unsqueeze(2) * Y.unsqueeze(1)).sum(0)  # sum_k X[k, i] Y[k, j]
    return (X.unsqueeze(2) * Y.unsqueeze(0)).sum(1)  # sum_k X[i, k] Y[k, j]


def quat_multiply(a: Tensor, b: Tensor, dim: int = -1, execution: Execution = COMPILED) -> Tensor:
    """Hamilton product a * b of wxyz quaternions along `dim` ([..., 4] by default; dim=0 for component-major
    [4, N], whose components are contiguous rows) (rotation b first, then a)."""
    if few_kernels(a, execution) and dim in (0, -1):
        return _bilinear(a, b, dim, _HAMILTON_INDEX, _HAMILTON_COEF)
    aw, ax, ay, az = a.unbind(dim)
    bw, bx, by, bz = b.unbind(dim)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=dim,
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
    """[..., 3, 3] rotation -> [..., 4] wxyz with w >= 0 (`rotmat_to_quat_entry_major` on a transposed view)."""
    return rotmat_to_quat_entry_major(R.reshape(-1, 9).t()).t().reshape(*R.shape[:-2], 4)


def _argmax_of_four(v: Tensor) -> Tensor:
    """argmax over the first four rows of v [>= 4, M] (the first on ties) by three comparisons: torch's argmax over
    a 4-long dimension is an order of magnitude slower than these few vector operations."""
    first, m01 = (v[1] > v[0]).long(), torch.maximum(v[0], v[1])
    second, m23 = (v[3] > v[2]).long() + 2, torch.maximum(v[2], v[3])
    return torch.where(m23 > m01, second, first)


def rotmat_to_quat_entry_major(R: Tensor) -> Tensor:
    """Entry-major rotations [9, M] (row 3i + j = entry (i, j)) -> [4, M] wxyz with w >= 0.

    Of the four rows of 4 q q^T that R gives linearly, it takes the one with the largest diagonal entry 4 q_k^2 >= 1
    (the best-conditioned formula, as pytorch3d) and normalises it: no square root and no division by a small number,
    so values and gradients stay finite for every rotation, 180 degrees included. One product and one gather instead of
    sixteen stacked candidate entries (about twice as fast, three times with the backward); values and gradients equal
    the sixteen-entry form's to 1e-15 in float64."""
    offset, mix = (constant_on(t, R.device, R.dtype) for t in (_ROTMAT_QUAT_OFFSET, _ROTMAT_QUAT_MIX))
    vals = torch.addmm(offset[:, None], mix.t(), R)  # [10, M]
    best = _argmax_of_four(vals)  # [M]
    q = vals.gather(0, constant_on(_ROTMAT_QUAT_ROWS, best.device).t()[:, best])  # [4, M] = 4 q_k (+-q)
    q = q * q.square().sum(0).rsqrt()  # |4 q_k q| = 4 q_k^2 >= 1: never zero
    return torch.where(q[:1] < 0, -q, q)


def axis_angle_to_rotmat(aa: Tensor, execution: Execution = COMPILED) -> Tensor:
    """[..., 3] axis-angle -> [..., 3, 3] (Rodrigues), with finite values and gradients at zero angle."""
    if aa.requires_grad and few_kernels(aa, execution):
        return _AxisAngleToRotmat.apply(aa)
    return _rodrigues(aa)[0]


def _rodrigues(aa: Tensor, derivatives: bool = False) -> tuple[Tensor, ...]:
    """R = I + a K + b K^2 [..., 3, 3] of axis-angle aa [..., 3], with K = [aa]x [..., 3, 3], a = sin(t) / t and
    b = (1 - cos(t)) / t^2 [..., 1] (t^2 = aa . aa; Taylor terms below AXIS_ANGLE_TAYLOR_SQ). Returns (R,), or with
    `derivatives` (R, K, a, b, a', b'): a' and b' [..., 1] are the derivatives in t^2 (of the Taylor terms below)."""
    theta2 = (aa * aa).sum(-1, keepdim=True)  # [..., 1]
    small = theta2 < AXIS_ANGLE_TAYLOR_SQ
    theta2_safe = torch.where(small, torch.ones_like(theta2), theta2)
    theta = torch.sqrt(theta2_safe)
    # sin(t)/t and (1-cos(t))/t^2 with Taylor expansions near zero (in this order: autograd's CPU gradients sum in it)
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta2_safe)
    x, y, z = aa.unbind(-1)
    zero = torch.zeros_like(x)
    K = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(*aa.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=aa.dtype, device=aa.device).expand_as(K)
    R = eye + a[..., None] * K + b[..., None] * (K @ K)
    if not derivatives:
        return (R,)
    a_s = torch.where(small, torch.full_like(theta2, -1 / 6), (torch.cos(theta) - a) / (2 * theta2_safe))
    b_s = torch.where(small, torch.full_like(theta2, -1 / 24), (a - 2 * b) / (2 * theta2_safe))
    return R, K, a, b, a_s, b_s


class _AxisAngleToRotmat(torch.autograd.Function):
    """`axis_angle_to_rotmat` with its closed-form backward on accelerators. With s = t^2,
    dR/dr_i = 2 r_i (a' K + b' K^2) + a [e_i]x + b ([e_i]x K + K [e_i]x), so
    dL/dr = 2 r (a' <G, K> + b' <G, K^2>) + vee(a G - b (G K + K G)), where vee(M) = (M21 - M12, M02 - M20, M10 - M01)
    is <M, [e_i]x>: 41 operators backward where autograd through the forward issues 77 (50 forward against 39: the
    derivatives of a and b). The CPU keeps autograd's."""

    @staticmethod
    def forward(ctx, aa: Tensor) -> Tensor:  # type: ignore[override]
        R, K, a, b, a_s, b_s = _rodrigues(aa, derivatives=True)
        ctx.save_for_backward(aa, K, a, b, a_s, b_s)
        return R

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, G: Tensor) -> Tensor:  # type: ignore[override]
        aa, K, a, b, a_s, b_s = ctx.saved_tensors
        K2 = K @ K  # [..., 3, 3]
        radial = a_s * (G * K).sum((-2, -1)).unsqueeze(-1) + b_s * (G * K2).sum((-2, -1)).unsqueeze(-1)  # [..., 1]
        M = (a.unsqueeze(-1) * G - b.unsqueeze(-1) * (G @ K + K @ G)).flatten(-2)  # [..., 9]
        plus, minus = (constant_on(t, M.device) for t in (_VEE_PLUS, _VEE_MINUS))
        return 2 * aa * radial + M.index_select(-1, plus) - M.index_select(-1, minus)


# vee(M) for a row-major flattened 3x3 M: entries (2,1), (0,2), (1,0) minus entries (1,2), (2,0), (0,1)
_VEE_PLUS = torch.tensor([7, 2, 3])
_VEE_MINUS = torch.tensor([5, 6, 1])
