"""Polar decomposition A = R S of 3x3 matrices (R a rotation, S symmetric) with well-defined gradients.

Why not autograd through SVD: for the blended transforms of linear blend skinning the singular values usually
coincide (a rigid blend has s = (1, 1, 1)), where the gradients of U and V are undefined (division by s_i - s_j).
The rotational part itself is perfectly differentiable there: its derivative only divides by s_i + s_j. So:

- Forward (no autograd, float64): a batched SVD by default (only its values are used, which are well defined), or
  Higham's scaled Newton iteration X <- (z X + X^-T / z) / 2 with Frobenius scaling
  z = sqrt(|X^-1| / |X|); it converges quadratically to the orthogonal polar factor and costs a few 3x3 adjugates.
  Matrices it cannot handle -- det(A) <= 0 (a reflection: we return the closest *proper* rotation,
  U diag(1, 1, det(U V^T)) V^T) or nearly singular (e.g. a 50/50 blend of antipodal bone rotations, which is rank 1)
  -- are routed to a float64 SVD on that subset only, whose *values* are fine.
- Backward (closed form): with dR = R [w]x and S symmetric, the skew part of R^T dA gives
  S [w]x + [w]x S = [(tr(S) I - S) w]x, so w = (tr(S) I - S)^-1 vee(R^T dA - dA^T R) and
  dL/dA = R [h]x with h = (tr(S) I - S)^-1 vee(R^T G - G^T R), G = dL/dR. The 3x3 solve is Tikhonov-regularised,
  h = B (B^2 + d^2 I)^-1 g with d = 1e-3 tr(S), so at rank-deficient A (where the rotation is not determined) the
  gradient stays finite and bounded (by |g| / 2d) instead of blowing up; elsewhere the bias is ~ (d / (s_i + s_j))^2.
"""

from __future__ import annotations

import torch
from torch import Tensor

from framework.guards import POLAR_DAMPING_FLOOR, POLAR_SINGULAR_TOL, POLAR_TIKHONOV

_NEWTON_MAX_ITERS = 30
_NEWTON_TOL = 1e-13


def _cross_rows(a: Tensor, b: Tensor) -> Tensor:
    """Cross product along dim 0 of [3, M] tensors (component-major layout: contiguous, fast elementwise ops)."""
    return torch.stack([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _skew(v: Tensor) -> Tensor:
    """[..., 3] -> [..., 3, 3] with skew(v) @ x = v x x."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(*v.shape, 3)


def _vee(K: Tensor) -> Tensor:
    """Inverse of `_skew` on the skew part's lower entries: (K21, K02, K10) [..., 3]."""
    return torch.stack([K[..., 2, 1], K[..., 0, 2], K[..., 1, 0]], dim=-1)


def _rotation_svd(A: Tensor) -> Tensor:
    """Closest proper rotation by SVD (values only), [M, 3, 3] float64."""
    U, _, Vh = torch.linalg.svd(A)
    d = torch.where(torch.linalg.det(U @ Vh) < 0, -1.0, 1.0).to(A.dtype)
    U = torch.cat([U[..., :2], U[..., 2:] * d[..., None, None]], dim=-1)
    return U @ Vh


def _rotation_newton(A: Tensor) -> Tensor:
    """Orthogonal polar factor of well-conditioned A with det > 0, [M, 3, 3] float64.

    Works in a component-major layout X[i, j, m] so each step is a few dozen contiguous vector operations.
    """
    X = A.permute(1, 2, 0).contiguous()  # [3, 3, M]
    for _ in range(_NEWTON_MAX_ITERS):
        C = torch.stack([_cross_rows(X[1], X[2]), _cross_rows(X[2], X[0]), _cross_rows(X[0], X[1])])  # cofactors
        det = (X[0] * C[0]).sum(0)  # [M]
        X_inv_T = C / det
        zeta = torch.sqrt(X_inv_T.square().sum((0, 1)).sqrt() / X.square().sum((0, 1)).sqrt())  # [M]
        X_new = 0.5 * (zeta * X + X_inv_T / zeta)
        delta = float((X_new - X).abs().amax())
        X = X_new
        if delta < _NEWTON_TOL:
            break
    return X.permute(2, 0, 1)


@torch.no_grad()
def polar_rotation_values(A: Tensor, method: str = "svd") -> Tensor:
    """Rotation factor of A [..., 3, 3] (values only, float64 inside, returned in A's dtype).

    method="svd": one batched LAPACK call (measured faster on CPU: 50k matrices ~0.4 s vs ~1.2 s for Newton on a
    loaded 2-core machine); method="newton": Higham's iteration, SVD only for det <= 0 or nearly singular inputs.
    Both give the same values to ~1e-14; the gradient is the same closed form either way.
    """
    if method not in ("svd", "newton"):
        raise ValueError(f"polar: method must be 'svd' or 'newton', got '{method}'.")
    shape, dtype = A.shape, A.dtype
    A64 = A.detach().reshape(-1, 3, 3).double()
    if A64.shape[0] == 0:
        return torch.empty(shape, dtype=dtype, device=A.device)
    finite = torch.isfinite(A64).flatten(1).all(1)
    A64 = torch.where(finite[:, None, None], A64, torch.eye(3, dtype=A64.dtype, device=A64.device).expand_as(A64))
    if method == "svd":
        return _rotation_svd(A64).reshape(shape).to(dtype)
    R = torch.empty_like(A64)
    det = torch.linalg.det(A64)
    scale = A64.flatten(1).norm(dim=1) / 3**0.5
    good = det > POLAR_SINGULAR_TOL * scale**3
    if good.any():
        R[good] = _rotation_newton(A64[good])
    if (~good).any():
        R[~good] = _rotation_svd(A64[~good])
    return R.reshape(shape).to(dtype)


class _PolarRotation(torch.autograd.Function):
    @staticmethod
    def forward(ctx, A: Tensor) -> Tensor:
        R = polar_rotation_values(A)
        ctx.save_for_backward(A, R)
        return R

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_R: Tensor) -> Tensor:
        A, R = ctx.saved_tensors
        A64, R64, G = A.double(), R.double(), grad_R.double()
        S = R64.transpose(-1, -2) @ A64
        S = 0.5 * (S + S.transpose(-1, -2))
        tr = S.diagonal(dim1=-2, dim2=-1).sum(-1)  # [...]
        eye = torch.eye(3, dtype=S.dtype, device=S.device)
        B = tr[..., None, None] * eye - S  # [..., 3, 3] symmetric
        g = _vee(R64.transpose(-1, -2) @ G - G.transpose(-1, -2) @ R64)  # [..., 3]
        d2 = (POLAR_TIKHONOV * tr.abs()) ** 2 + POLAR_DAMPING_FLOOR
        h = torch.linalg.solve(B @ B + d2[..., None, None] * eye, (B @ g.unsqueeze(-1))).squeeze(-1)
        grad_A = R64 @ _skew(h)
        grad_A = torch.where(torch.isfinite(grad_A), grad_A, torch.zeros_like(grad_A))
        big = torch.finfo(A.dtype).max  # half precision: saturate rather than overflow to inf
        return grad_A.clamp(-big, big).to(A.dtype)


def polar_rotation(A: Tensor) -> Tensor:
    """Rotation factor R of A = R S, [..., 3, 3] -> [..., 3, 3], differentiable with the closed-form gradient."""
    if A.shape[-2:] != (3, 3):
        raise ValueError(f"polar_rotation: expected matrices [..., 3, 3], got shape {tuple(A.shape)}.")
    return _PolarRotation.apply(A)


def polar_decompose(A: Tensor) -> tuple[Tensor, Tensor]:
    """A [..., 3, 3] -> (R, S): R a proper rotation, S = R^T A symmetrised (positive semi-definite when det A >= 0).

    For det(A) < 0 (a reflection; not produced by valid blends) R is the closest proper rotation and S has one
    negative eigenvalue.
    """
    R = polar_rotation(A)
    S = R.transpose(-1, -2) @ A
    return R, 0.5 * (S + S.transpose(-1, -2))
