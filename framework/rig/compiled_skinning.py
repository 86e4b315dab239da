"""`framework.rig.lbs.lbs_with_sh_frames` for baked weights without gradients, as one compiled loop (numba).

Why: once the rasterizer runs compiled (`rasterizer=numba`), the skinning is the largest part of a CPU novel-pose
frame. On the walking avatars at 128² it took 3.8-5.8 ms. About half of that is fixed: some 600 small tensor
operations (the blend, the polar iteration, the quaternions and the stretch), whatever the Gaussian count. Per Gaussian
the work is a 12-wide blend and a few 3x3 products, which one pass does without per-operation overhead.

The same rules as `framework.rig.lbs` and `framework.rig.polar`, in float64:
- the blend P = sum_k w_k P_k (over the non-zero weights: a non-finite bone transform reaches only the Gaussians
  it weights, where torch's matrix product spreads NaN * 0 to all of them);
- the rotation of A = R S by Higham's scaled Newton iteration, per matrix. It stops when the step it just took,
  squared, is below 1e-13. A matrix with det(A) <= 1e-6 (|A|_F / sqrt 3)^3 (a reflection or nearly singular) gets the
  closest proper rotation from the SVD, and a non-finite one the identity;
- R's quaternion from the best-conditioned row of 4 q q^T (w >= 0);
- the centres (A x + t, or R x + t for centres="rigid"), the quaternions qR * q / |q|, and the stretch
  k_l = a_l^T R^T A a_l on the log-scales, floored at LBS_MIN_STRETCH.
The torch path iterates the polar decomposition in float32 by default, and all of its matrices until the slowest has
converged. Its results agree with these to float32 rounding (`tests/test_compiled_skinning.py` checks that against the
torch path in float64).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from framework.guards import LBS_MIN_STRETCH, NORM_EPS, POLAR_SINGULAR_TOL

_NEWTON_MAX_ITERS = 30
_NEWTON_TOL = 1e-13  # float64, as framework.rig.polar


@njit(cache=True, nogil=True)
def _cofactors_det_norm(X, C) -> tuple[float, float]:
    """C = cofactor matrix of the 3x3 X (row i is the cross product of rows i + 1 and i + 2); returns (det X,
    |X|_F^2), which every step of the iteration needs with it."""
    for i in range(3):
        i1, i2 = (i + 1) % 3, (i + 2) % 3
        for k in range(3):
            k1, k2 = (k + 1) % 3, (k + 2) % 3
            C[i, k] = X[i1, k1] * X[i2, k2] - X[i1, k2] * X[i2, k1]
    norm_sq = 0.0
    for i in range(3):
        for j in range(3):
            norm_sq += X[i, j] * X[i, j]
    return X[0, 0] * C[0, 0] + X[0, 1] * C[0, 1] + X[0, 2] * C[0, 2], norm_sq


@njit(cache=True, nogil=True)
def _polar_rotation(A, R, X, C) -> None:
    """R = the rotation factor of A = R S (the rules of framework.rig.polar, per matrix); X, C: [3, 3] work space."""
    finite = True
    for i in range(3):
        for j in range(3):
            finite = finite and math.isfinite(A[i, j])
    for i in range(3):
        for j in range(3):
            X[i, j] = A[i, j] if finite else (1.0 if i == j else 0.0)
    det, norm_sq = _cofactors_det_norm(X, C)
    mean_sq = norm_sq / 3.0
    if not det > POLAR_SINGULAR_TOL * mean_sq * math.sqrt(mean_sq):
        U, _, Vh = np.linalg.svd(X)  # the closest proper rotation: U diag(1, 1, det(U V^T)) V^T
        if np.linalg.det(U @ Vh) < 0:
            U[:, 2] = -U[:, 2]
        M = U @ Vh
        for i in range(3):
            for j in range(3):
                R[i, j] = M[i, j]
        return
    for it in range(_NEWTON_MAX_ITERS):
        if it:
            det, norm_sq = _cofactors_det_norm(X, C)
        c_sq = 0.0
        for i in range(3):
            for j in range(3):
                c_sq += C[i, j] * C[i, j]
        zeta = math.sqrt(math.sqrt(c_sq / norm_sq)) / math.sqrt(det)
        step = 0.0
        for i in range(3):
            for j in range(3):
                new = 0.5 * zeta * X[i, j] + 0.5 / (zeta * det) * C[i, j]
                step = max(step, abs(new - X[i, j]))
                X[i, j] = new
        if step * step < _NEWTON_TOL:
            break
    for i in range(3):
        for j in range(3):
            R[i, j] = X[i, j]


@njit(cache=True, nogil=True)
def _rotmat_to_quat(R, q) -> None:
    """q (wxyz, w >= 0) of the rotation R, from the row of 4 q q^T with the largest diagonal entry."""
    v0 = 1.0 + R[0, 0] + R[1, 1] + R[2, 2]
    v1 = 1.0 + R[0, 0] - R[1, 1] - R[2, 2]
    v2 = 1.0 - R[0, 0] + R[1, 1] - R[2, 2]
    v3 = 1.0 - R[0, 0] - R[1, 1] + R[2, 2]
    wx, wy, wz = R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]
    xy, xz, yz = R[1, 0] + R[0, 1], R[0, 2] + R[2, 0], R[1, 2] + R[2, 1]
    first, m01 = (1 if v1 > v0 else 0), max(v0, v1)
    second, m23 = (3 if v3 > v2 else 2), max(v2, v3)
    best = second if m23 > m01 else first
    if best == 0:
        a, b, c, d = v0, wx, wy, wz
    elif best == 1:
        a, b, c, d = wx, v1, xy, xz
    elif best == 2:
        a, b, c, d = wy, xy, v2, yz
    else:
        a, b, c, d = wz, xz, yz, v3
    s = 1.0 / math.sqrt(a * a + b * b + c * c + d * d)
    if a * s < 0:
        s = -s
    q[0], q[1], q[2], q[3] = a * s, b * s, c * s, d * s


@njit(cache=True, nogil=True)
def skin(weights, transforms, means, quats, log_scales, blended_centres, diag_stretch,
         out_means, out_quats, out_log_scales, out_rotations) -> None:  # fmt: skip
    """Pose N Gaussians: weights [N, J], transforms [J, 12] (rows of each bone's [3, 4]), means [N, 3], quats [N, 4]
    (wxyz, any norm), log_scales [N, 3] -> out_means [N, 3], out_quats [N, 4], out_log_scales [N, 3] and the
    rotations out_rotations [N, 3, 3] (the SH frames)."""
    N, J = weights.shape
    P = np.empty(12)
    A = np.empty((3, 3))
    R = np.empty((3, 3))
    Q = np.empty((3, 3))
    X = np.empty((3, 3))
    C = np.empty((3, 3))
    qR = np.empty(4)
    for n in range(N):
        P[:] = 0.0
        for k in range(J):
            w = weights[n, k]
            if w != 0.0:
                for e in range(12):
                    P[e] += w * transforms[k, e]
        for i in range(3):
            for j in range(3):
                A[i, j] = P[4 * i + j]
        _polar_rotation(A, R, X, C)
        _rotmat_to_quat(R, qR)
        x0, x1, x2 = means[n, 0], means[n, 1], means[n, 2]
        for i in range(3):
            m = A if blended_centres else R
            out_means[n, i] = m[i, 0] * x0 + m[i, 1] * x1 + m[i, 2] * x2 + P[4 * i + 3]
        w, qx, qy, qz = quats[n, 0], quats[n, 1], quats[n, 2], quats[n, 3]
        qn = math.sqrt(max(w * w + qx * qx + qy * qy + qz * qz, NORM_EPS * NORM_EPS))
        if qn > NORM_EPS:
            w, qx, qy, qz = w / qn, qx / qn, qy / qn, qz / qn
        else:
            w, qx, qy, qz = 1.0, 0.0, 0.0, 0.0
        aw, ax, ay, az = qR[0], qR[1], qR[2], qR[3]
        out_quats[n, 0] = aw * w - ax * qx - ay * qy - az * qz
        out_quats[n, 1] = aw * qx + ax * w + ay * qz - az * qy
        out_quats[n, 2] = aw * qy - ax * qz + ay * w + az * qx
        out_quats[n, 3] = aw * qz + ax * qy - ay * qx + az * w
        for i in range(3):
            for j in range(3):
                out_rotations[n, i, j] = R[i, j]
        if not diag_stretch:
            for l in range(3):  # noqa: E741
                out_log_scales[n, l] = log_scales[n, l]
            continue
        # the Gaussian's axes a_l (columns of its rotation) and k_l = a_l^T (R^T A) a_l
        Q[0, 0], Q[0, 1], Q[0, 2] = 1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - w * qz), 2 * (qx * qz + w * qy)
        Q[1, 0], Q[1, 1], Q[1, 2] = 2 * (qx * qy + w * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - w * qx)
        Q[2, 0], Q[2, 1], Q[2, 2] = 2 * (qx * qz - w * qy), 2 * (qy * qz + w * qx), 1 - 2 * (qx * qx + qy * qy)
        for l in range(3):  # noqa: E741
            k = 0.0
            for i in range(3):
                ra = 0.0  # (R^T A a_l)_i
                for j in range(3):
                    ra += (R[0, i] * A[0, j] + R[1, i] * A[1, j] + R[2, i] * A[2, j]) * Q[j, l]
                k += Q[i, l] * ra
            out_log_scales[n, l] = log_scales[n, l] + math.log(max(k, LBS_MIN_STRETCH))


def lbs_with_sh_frames_compiled(gaussians, weights, transforms, stretch: str = "diag", centres: str = "blended"):
    """`framework.rig.lbs.lbs_with_sh_frames` (posed Gaussians with canonical SH, R [N, 3, 3]) through `skin`: no
    gradients, CPU tensors; results in the Gaussians' dtype."""
    import torch

    from framework.splat.compiled_cpu import float64_array as f64

    N, dtype = gaussians.means.shape[0], gaussians.means.dtype
    out_means, out_quats, out_log_scales = np.empty((N, 3)), np.empty((N, 4)), np.empty((N, 3))
    out_rotations = np.empty((N, 3, 3))
    skin(f64(weights), f64(transforms[:, :3, :].reshape(-1, 12)), f64(gaussians.means), f64(gaussians.quats),
         f64(gaussians.log_scales), centres == "blended", stretch == "diag", out_means, out_quats, out_log_scales,
         out_rotations)  # fmt: skip
    posed = gaussians.replace(
        means=torch.from_numpy(out_means).to(dtype),
        quats=torch.from_numpy(out_quats).to(dtype),
        log_scales=torch.from_numpy(out_log_scales).to(dtype),
    )
    return posed, torch.from_numpy(out_rotations).to(dtype)
