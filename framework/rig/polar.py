"""Polar decomposition A = R S of 3x3 matrices (R a rotation, S symmetric) with well-defined gradients.

Why not autograd through SVD: for the blended transforms of linear blend skinning the singular values usually
coincide (a rigid blend has s = (1, 1, 1)), where the gradients of U and V are undefined (division by s_i - s_j).
The rotational part itself is perfectly differentiable there: its derivative only divides by s_i + s_j. So:

- Forward (no autograd): Higham's scaled Newton iteration X <- (z X + X^-T / z) / 2 with Frobenius scaling
  z = sqrt(|X^-1| / |X|); it converges quadratically to the orthogonal polar factor and costs a few 3x3 adjugates,
  written as contiguous vector operations on an entry-major [9, M] layout (no LAPACK call per matrix). It runs in the
  compute dtype: float32 by default for float32 inputs (measured on 8k LBS blends: max |R - R_float64| ~ 1e-6; a
  float32 rotation stored from a float64 computation is within 6e-8 of it), float64 on request (`dtype=`) and for
  float64 inputs. Matrices it cannot handle -- det(A) <= 0 (a reflection: we return the closest *proper* rotation,
  U diag(1, 1, det(U V^T)) V^T) or nearly singular (e.g. a 50/50 blend of antipodal bone rotations, which is rank 1)
  -- are routed to a float64 SVD on that subset only, whose *values* are fine. method="svd" runs the float64 SVD on
  everything (the reference; measured 2.4x slower than float64 Newton on 8k matrices on one CPU core).
- Backward (closed form): with dR = R [w]x and S symmetric, the skew part of R^T dA gives
  S [w]x + [w]x S = [(tr(S) I - S) w]x, so w = (tr(S) I - S)^-1 vee(R^T dA - dA^T R) and
  dL/dA = R [h]x with h = (tr(S) I - S)^-1 vee(R^T G - G^T R), G = dL/dR. The 3x3 solve is Tikhonov-regularised,
  h = B (B^2 + d^2 I)^-1 g with d = 1e-3 tr(S), so at rank-deficient A (where the rotation is not determined) the
  gradient stays finite and bounded (by |g| / 2d) instead of blowing up; elsewhere the bias is ~ (d / (s_i + s_j))^2.
  It is evaluated in float64 with the symmetric 3x3 adjugate (Cramer's rule), as vector operations over the batch.
"""

from __future__ import annotations

import torch
from torch import Tensor

from framework.device_constants import constant_on
from framework.execution import COMPILED, Execution
from framework.geometry import products_3x3
from framework.guards import POLAR_DAMPING_FLOOR, POLAR_SINGULAR_TOL, POLAR_TIKHONOV

_NEWTON_MAX_ITERS = 30
# The iteration ends when the step it just took, d = max |X_k+1 - X_k|, predicts a next step below this tolerance. The
# convergence is quadratic (|X_k+2 - X_k+1| ~ d^2 / 2 once X is near orthogonal), so d^2 < tol suffices and the step
# that would only confirm it is not taken.
_NEWTON_TOL = {torch.float64: 1e-13, torch.float32: 1e-6}
# On an accelerator every check is a host sync that drains the queue, so there the iteration takes this many steps
# unchecked and then reads ONE value on the host: whether every matrix was fit for Newton (the routing test below) and
# the last step predicts convergence. LBS blends are close to orthogonal (smallest singular value 0.70-0.999 over the
# walking avatar's frames); the checked iteration stops after 1-3 steps on them (32 training and novel-pose frames:
# 3 steps at most with the predicted stop), so 4 steps pass the check with a step to spare, and a step more costs
# about ten element-wise kernels where a sync waits for everything queued. Measured in float32: 4 steps converge for
# singular-value ratios down to 0.1 (0.7: 3 steps, 0.01: 5). Batches that need more fail the read and take the
# checked path, which costs a sync per step as on the CPU.
_NEWTON_STEPS_ACCELERATOR = 4


def _cofactor_index() -> Tensor:
    """Rows of X [9, M] (entry 3i + j of each matrix) whose products give the cofactors, as one [36] index.

    Row i of the cofactor matrix is the cross product of rows i + 1 and i + 2 (mod 3), so its entry k is
    X[i+1, k+1] X[i+2, k+2] - X[i+1, k+2] X[i+2, k+1]; the four [9] blocks list those four factors for every entry."""
    blocks: list[list[int]] = [[], [], [], []]
    for i in range(3):
        for k in range(3):
            i1, i2, k1, k2 = (i + 1) % 3, (i + 2) % 3, (k + 1) % 3, (k + 2) % 3
            for block, entry in zip(blocks, (3 * i1 + k1, 3 * i2 + k2, 3 * i1 + k2, 3 * i2 + k1), strict=True):
                block.append(entry)
    return torch.tensor(sum(blocks, []))


_COFACTOR_INDEX = _cofactor_index()  # [36]


def _cofactors(X: Tensor) -> Tensor:
    """Cofactor matrices of X [9, M] (entry-major: every op is one contiguous vector operation), [9, M].

    One gather of the 36 factor rows and one fused multiply-subtract, instead of 27 products on single entries."""
    a, b, c, d = X.index_select(0, constant_on(_COFACTOR_INDEX, X.device)).view(4, 9, -1).unbind(0)  # 4 x [9, M]
    return torch.addcmul(a * b, c, d, value=-1.0)


def _rotation_svd(A: Tensor) -> Tensor:
    """Closest proper rotation by SVD (values only), [M, 3, 3] float64."""
    U, _, Vh = torch.linalg.svd(A)
    d = torch.where(torch.linalg.det(U @ Vh) < 0, -1.0, 1.0).to(A.dtype)
    U = torch.cat([U[..., :2], U[..., 2:] * d[..., None, None]], dim=-1)
    return U @ Vh


def _newton_step(X: Tensor, C: Tensor, det: Tensor, norm_sq: Tensor) -> Tensor:
    """One scaled Newton step on entry-major X [9, M] -> [9, M], given X's cofactors [9, M], determinants [M] and
    squared Frobenius norms [M]. X^-T = C / det, so the step is X <- (z / 2) X + (1 / (2 z det)) C with
    z = sqrt(|X^-1| / |X|) = (|C|^2 / |X|^2)^(1/4) / sqrt(det): per-matrix scalars and one fused multiply-add. (In
    that order, float32 stays in range for |X| up to ~1e9: det^2 |X|^2 would overflow from |X| ~ 1e5.)"""
    zeta = (C.square().sum(0) / norm_sq).sqrt().sqrt() * det.rsqrt()  # [M] (sqrt twice: pow(0.25) is 4x slower)
    return torch.addcmul(X * (0.5 * zeta), C, 0.5 / (zeta * det))


def _cofactors_det_norm(X: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Cofactors [9, M], determinants [M] and squared Frobenius norms [M] of X [9, M]."""
    C = _cofactors(X)
    return C, (X[:3] * C[:3]).sum(0), X.square().sum(0)


def _rotation_newton(X: Tensor, C: Tensor, det: Tensor, norm_sq: Tensor) -> Tensor:
    """Orthogonal polar factor of well-conditioned matrices with det > 0, entry-major [9, M] -> [9, M] in X's dtype,
    checked after every step (a host read each; free on a CPU). C, det, norm_sq: X's, which the caller has computed
    for its singularity test."""
    tol = _NEWTON_TOL.get(X.dtype, 1e-6)
    for it in range(_NEWTON_MAX_ITERS):
        if it:
            C, det, norm_sq = _cofactors_det_norm(X)
        X_new = _newton_step(X, C, det, norm_sq)
        done = float((X_new - X).abs().amax()) ** 2 < tol
        X = X_new
        if done:
            break
    return X


def _rotation_newton_one_read(X: Tensor, C: Tensor, det: Tensor, norm_sq: Tensor, good: Tensor) -> Tensor | None:
    """The accelerator's form of `_polar_values_entry_major`'s common case: `_NEWTON_STEPS_ACCELERATOR` unchecked
    steps on every matrix, then one host read of "every matrix good and converged". Returns the polar factors
    [9, M], or None when that read is False (a matrix for the SVD, a non-finite entry, or slow convergence: the
    caller then takes the checked path from the start; the steps here were spent on nothing)."""
    tol = _NEWTON_TOL.get(X.dtype, 1e-6)
    for it in range(_NEWTON_STEPS_ACCELERATOR - 1):
        if it:
            C, det, norm_sq = _cofactors_det_norm(X)
        X = _newton_step(X, C, det, norm_sq)
    X_new = _newton_step(X, *_cofactors_det_norm(X))
    last_step = (X_new - X).abs().amax()  # [], NaN where a matrix was not fit for Newton
    return X_new if bool((last_step.square() < tol) & good.all()) else None


def _finite_or_identity(X: Tensor) -> Tensor:
    """X [9, M] with every matrix holding a NaN or inf entry replaced by the identity."""
    if bool(torch.isfinite(X.sum())):  # one reduction: NaN and inf propagate (an overflow only costs the check)
        return X
    eye = torch.eye(3, dtype=X.dtype, device=X.device).reshape(9, 1)
    return torch.where(torch.isfinite(X).all(0), X, eye)


def _newton_inputs(X: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Cofactors [9, M], determinants [M], squared norms [M] of X [9, M], and which matrices Newton may take [M]:
    det > tol * scale^3 (well-conditioned, det > 0)."""
    C, det, norm_sq = _cofactors_det_norm(X)  # [9, M], [M], [M]
    mean_sq = norm_sq / 3
    return C, det, norm_sq, det > POLAR_SINGULAR_TOL * mean_sq * mean_sq.sqrt()


def _compute_dtype(X: Tensor, dtype: torch.dtype | None) -> torch.dtype:
    """The iteration's dtype: `dtype`, else X's and at least float32; float32 or float64 only."""
    compute = dtype or torch.promote_types(X.dtype, torch.float32)
    if compute not in (torch.float32, torch.float64):
        raise ValueError(f"polar: dtype must be torch.float32 or torch.float64, got {compute}.")
    return compute


@torch.no_grad()
def polar_rotation_values(
    A: Tensor, method: str = "newton", dtype: torch.dtype | None = None, execution: Execution = COMPILED
) -> Tensor:
    """Rotation factor of A [..., 3, 3] (values only), returned in A's dtype.

    method="newton": Higham's iteration in `dtype` (default: A's dtype, at least float32), float64 SVD only for
    det <= 0 or nearly singular inputs; method="svd": float64 SVD for every matrix (the reference). Both agree to
    ~1e-14 in float64 and ~1e-6 with a float32 iteration.
    """
    X = A.detach().reshape(-1, 9).t()  # [9, M]
    return _polar_values_entry_major(X, method, dtype, execution).t().reshape(A.shape)


@torch.no_grad()
def _polar_values_entry_major(
    X: Tensor, method: str = "newton", dtype: torch.dtype | None = None, execution: Execution = COMPILED
) -> Tensor:
    """`polar_rotation_values` on entry-major matrices: X [9, M] (entry 3i + j of each matrix) -> R [9, M].
    `execution`: a matrix batch it does not compile takes an accelerator's routing (one host read)."""
    if method not in ("svd", "newton"):
        raise ValueError(f"polar: method must be 'svd' or 'newton', got '{method}'.")
    out_dtype, M = X.dtype, X.shape[1]
    compute = _compute_dtype(X, dtype)
    Xc = X.to(torch.float64 if method == "svd" else compute).contiguous()  # [9, M]
    if M == 0:
        return torch.empty_like(X)
    if method == "svd":
        return _rotation_svd(_finite_or_identity(Xc).t().reshape(-1, 3, 3)).reshape(M, 9).t().to(out_dtype)
    C, det, norm_sq, good = _newton_inputs(Xc)
    # The common case: `good` is False for any matrix with a NaN or inf entry, or whose squares overflow (its det or
    # scale is then NaN or inf), so all-good also means all finite. On an accelerator (and on a CPU under the torch
    # execution) it costs one host read in all; on a CPU a read per step, each free, and no step more than needed.
    if not execution.compiled(Xc):
        R = _rotation_newton_one_read(Xc, C, det, norm_sq, good)
        if R is not None:
            return R.to(out_dtype)
    if bool(good.all()):
        return _rotation_newton(Xc, C, det, norm_sq).to(out_dtype)
    Xc = _finite_or_identity(Xc)
    C, det, norm_sq, good = _newton_inputs(Xc)
    R = torch.empty_like(Xc)
    if good.any():
        R[:, good] = _rotation_newton(Xc[:, good], C[:, good], det[good], norm_sq[good])
    bad = Xc[:, ~good].t().reshape(-1, 3, 3).double()
    R[:, ~good] = _rotation_svd(bad).reshape(-1, 9).t().to(R.dtype)
    return R.to(out_dtype)


def _solve_sym3(M: Tensor, b: Tensor) -> Tensor:
    """x = M^-1 b for symmetric positive definite M [3, 3, K] and b [3, K], by the adjugate (Cramer's rule).

    The cofactors come from `_cofactors` (one gather, one fused multiply-subtract; for a symmetric M the adjugate is
    its cofactor matrix): eight kernels where the cofactors written out one by one took thirty."""
    K = M.shape[-1]
    C = _cofactors(M.reshape(9, K)).view(3, 3, K)  # [3, 3, K], symmetric
    det = (M[0] * C[0]).sum(0)  # [K], along the first row
    return (C * b.unsqueeze(0)).sum(1) / det  # [3, K]


def _skew_entry_major(v: Tensor) -> Tensor:
    """[3, K] -> [3, 3, K] with skew(v) x = v x x."""
    x, y, z = v.unbind(0)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o]).view(3, 3, -1)


class _PolarRotation(torch.autograd.Function):
    @staticmethod
    def forward(ctx, X: Tensor, dtype: torch.dtype | None, execution: Execution) -> Tensor:
        R = _polar_values_entry_major(X, dtype=dtype, execution=execution)
        ctx.save_for_backward(X, R)
        return R

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_R: Tensor) -> tuple[Tensor, None, None]:
        X, R = ctx.saved_tensors
        K = X.shape[1]
        A64, R64, G = (t.double().reshape(3, 3, K) for t in (X, R, grad_R))
        S = products_3x3(R64, A64, transpose_x=True)  # [3, 3, K] = R^T A
        S = 0.5 * (S + S.transpose(0, 1))
        tr = S[0, 0] + S[1, 1] + S[2, 2]  # [K]
        eye = torch.eye(3, dtype=S.dtype, device=S.device).unsqueeze(-1)  # [3, 3, 1]
        B = tr * eye - S  # [3, 3, K] symmetric
        RtG = products_3x3(R64, G, transpose_x=True)  # [3, 3, K]
        W = RtG - RtG.transpose(0, 1)
        g = torch.stack([W[2, 1], W[0, 2], W[1, 0]])  # [3, K], vee of the skew part
        d2 = (POLAR_TIKHONOV * tr.abs()) ** 2 + POLAR_DAMPING_FLOOR  # [K]
        h = _solve_sym3(products_3x3(B, B) + d2 * eye, (B * g.unsqueeze(0)).sum(1))  # [3, K]
        grad_X = products_3x3(R64, _skew_entry_major(h)).reshape(9, K)
        grad_X = torch.where(torch.isfinite(grad_X), grad_X, torch.zeros_like(grad_X))
        big = torch.finfo(X.dtype).max  # half precision: saturate rather than overflow to inf
        return grad_X.clamp(-big, big).to(X.dtype), None, None


def polar_rotation_entry_major(X: Tensor, dtype: torch.dtype | None = None, execution: Execution = COMPILED) -> Tensor:
    """Rotation factors of entry-major matrices, X [9, M] (row 3i + j = entry (i, j)) -> R [9, M], differentiable
    with the closed-form gradient.

    Why this layout: every step of the iteration and of its gradient is then a contiguous vector operation over the
    M matrices, where [M, 3, 3] batches run as many tiny 3x3 products."""
    if X.dim() != 2 or X.shape[0] != 9:
        raise ValueError(f"polar_rotation_entry_major: expected [9, M], got shape {tuple(X.shape)}.")
    return _PolarRotation.apply(X, dtype, execution)


def polar_rotation(A: Tensor, dtype: torch.dtype | None = None, execution: Execution = COMPILED) -> Tensor:
    """Rotation factor R of A = R S, [..., 3, 3] -> [..., 3, 3], differentiable with the closed-form gradient.

    `dtype`: the forward iteration's dtype (default A's, at least float32); the result has A's dtype."""
    if A.shape[-2:] != (3, 3):
        raise ValueError(f"polar_rotation: expected matrices [..., 3, 3], got shape {tuple(A.shape)}.")
    return polar_rotation_entry_major(A.reshape(-1, 9).t(), dtype, execution).t().reshape(A.shape)


def polar_decompose(
    A: Tensor, dtype: torch.dtype | None = None, execution: Execution = COMPILED
) -> tuple[Tensor, Tensor]:
    """A [..., 3, 3] -> (R, S): R a proper rotation, S = R^T A symmetrised (positive semi-definite when det A >= 0).

    For det(A) < 0 (a reflection; not produced by valid blends) R is the closest proper rotation and S has one
    negative eigenvalue.
    """
    R = polar_rotation(A, dtype, execution)
    S = R.transpose(-1, -2) @ A
    return R, 0.5 * (S + S.transpose(-1, -2))
