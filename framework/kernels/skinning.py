"""`framework.rig.lbs.lbs_with_sh_frames` as compiled loops (numba): for baked weights without gradients
(`lbs_with_sh_frames_compiled`, inference), and with a hand-written backward for training
(`lbs_with_sh_frames_trainable`).

Why: once the rasterizer runs compiled (`rasterizer=numba`), the skinning is the largest part of a CPU novel-pose
frame, and about half of it is fixed: some 600 small tensor
operations (the blend, the polar iteration, the quaternions and the stretch), whatever the Gaussian count. Per
Gaussian the work is a 12-wide blend and a few 3x3 products, which one pass does without per-operation overhead. For
inference the blend is one float64 matrix product when every bone transform is finite, the loop over the non-zero
weights otherwise.

The same rules as `framework.rig.lbs` and `framework.rig.polar`, in float64:
- the blend P = sum_k w_k P_k (with a non-finite bone transform, over the non-zero weights: it then reaches only the
  Gaussians it weights, where a matrix product spreads NaN * 0 to all of them);
- the rotation of A = R S by Higham's scaled Newton iteration, per matrix (64 matrices side by side, each taking
  exactly its own steps: `_polar_block`). It stops when the step it just took, squared, is below 1e-13. A matrix
  with det(A) <= 1e-6 (|A|_F / sqrt 3)^3 (a reflection or nearly singular) gets the closest proper rotation from the
  SVD, and a non-finite one the identity;
- R's quaternion from the best-conditioned row of 4 q q^T (w >= 0);
- the centres (A x + t, or R x + t for centres="rigid"), the quaternions qR * q / |q|, and the stretch
  k_l = a_l^T R^T A a_l on the log-scales, floored at LBS_MIN_STRETCH.
The torch path iterates the polar decomposition in float32 by default, and all of its matrices until the slowest has
converged. Its results agree with these to float32 rounding (`tests/test_compiled_skinning.py` checks that against the
torch path in float64).

Training: the blend stays torch's matrix product (`blended_affine`, whose backward reaches the weights and the bone
transforms); `skin_affine_forward` poses each Gaussian from its blended A and t as above, and `skin_affine_backward`
carries the outputs' gradients back through the stretch, the quaternion product, R's quaternion (the row the forward
took), the centres and the polar decomposition (the closed form of `framework.rig.polar`, per matrix) to A, t, the
means and the quaternions. In a stage-2 step the torch path runs some 300 small operations each way, about twice
these loops' time (docs/results/speed.md).
`tests/test_compiled_skinning_grad.py` checks values and gradients against the torch path in float64 and by finite
differences.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit

from framework.guards import LBS_MIN_STRETCH, NORM_EPS, POLAR_DAMPING_FLOOR, POLAR_SINGULAR_TOL, POLAR_TIKHONOV
from framework.kernels.threads import run_chunked

_NEWTON_MAX_ITERS = 30
_NEWTON_TOL = 1e-13  # float64, as framework.rig.polar


#: Gaussians whose polar iterations run side by side (`_polar_block`): wide enough for the vector units, small
#: enough that the block's matrices stay in L1
_BLOCK = 64
_PENDING, _DONE, _SINGULAR = 1, 0, 2  # a lane's state in `_polar_block`


@njit(cache=True, nogil=True, error_model="numpy")
def _polar_block(A9, start, stop, X, state) -> None:
    """X[:, k] = the rotation factor of A = R S (row-major, the rules of framework.rig.polar) for the Gaussians
    n = start + k < stop (at most X.shape[1] of them), A from A9 [9, N]; state [X.shape[1]] int8 work space.

    Why a block: per matrix, the iteration is a chain of dependent square roots and divisions, so one Gaussian at a
    time kept the core waiting on their latency (about 100 ns per Gaussian). Here each Newton step runs over the
    block's lanes in one straight loop, which the compiler vectorises. A lane that has converged keeps its matrix
    (the select below) while the others iterate, so each lane takes exactly the steps it would alone: the results
    equal the per-matrix iteration's bit for bit. `error_model="numpy"`: a division never raises (every divisor is
    positive where it is used), and so it has no branch that would keep the loop scalar."""
    m = stop - start
    for k in range(m):
        finite = True
        for e in range(9):
            finite = finite and math.isfinite(A9[e, start + k])
        for e in range(9):
            X[e, k] = A9[e, start + k] if finite else (1.0 if e % 4 == 0 else 0.0)  # a non-finite A: the identity
        state[k] = _PENDING
    for it in range(_NEWTON_MAX_ITERS):
        pending = 0
        for k in range(m):
            x00, x01, x02 = X[0, k], X[1, k], X[2, k]
            x10, x11, x12 = X[3, k], X[4, k], X[5, k]
            x20, x21, x22 = X[6, k], X[7, k], X[8, k]
            # the cofactor matrix (row i: the cross product of rows i + 1 and i + 2), det X, |X|_F^2 and |C|_F^2
            c00, c01, c02 = x11 * x22 - x12 * x21, x12 * x20 - x10 * x22, x10 * x21 - x11 * x20
            c10, c11, c12 = x21 * x02 - x22 * x01, x22 * x00 - x20 * x02, x20 * x01 - x21 * x00
            c20, c21, c22 = x01 * x12 - x02 * x11, x02 * x10 - x00 * x12, x00 * x11 - x01 * x10
            det = x00 * c00 + x01 * c01 + x02 * c02
            norm_sq = x00 * x00 + x01 * x01 + x02 * x02 + x10 * x10 + x11 * x11 + x12 * x12 + x20 * x20
            norm_sq = norm_sq + x21 * x21 + x22 * x22
            c_sq = c00 * c00 + c01 * c01 + c02 * c02 + c10 * c10 + c11 * c11 + c12 * c12 + c20 * c20
            c_sq = c_sq + c21 * c21 + c22 * c22
            s = state[k]
            if it == 0:  # a reflection or a nearly singular A: the SVD below
                mean_sq = norm_sq / 3.0
                s = s if det > POLAR_SINGULAR_TOL * mean_sq * math.sqrt(mean_sq) else _SINGULAR
            # Higham's scaled Newton step X <- (zeta X + C / (zeta det)) / 2
            zeta = math.sqrt(math.sqrt(c_sq / norm_sq)) / math.sqrt(det)
            a, b = 0.5 * zeta, 0.5 / (zeta * det)
            n00, n01, n02 = a * x00 + b * c00, a * x01 + b * c01, a * x02 + b * c02
            n10, n11, n12 = a * x10 + b * c10, a * x11 + b * c11, a * x12 + b * c12
            n20, n21, n22 = a * x20 + b * c20, a * x21 + b * c21, a * x22 + b * c22
            step = max(
                abs(n00 - x00),
                abs(n01 - x01),
                abs(n02 - x02),
                abs(n10 - x10),
                abs(n11 - x11),
                abs(n12 - x12),
                abs(n20 - x20),
                abs(n21 - x21),
                abs(n22 - x22),
            )
            go = s == _PENDING
            X[0, k], X[1, k], X[2, k] = (n00 if go else x00), (n01 if go else x01), (n02 if go else x02)
            X[3, k], X[4, k], X[5, k] = (n10 if go else x10), (n11 if go else x11), (n12 if go else x12)
            X[6, k], X[7, k], X[8, k] = (n20 if go else x20), (n21 if go else x21), (n22 if go else x22)
            s = _DONE if go and step * step < _NEWTON_TOL else s
            state[k] = s
            pending += 1 if s == _PENDING else 0
        if pending == 0:
            break
    for k in range(m):
        if state[k] == _SINGULAR:  # the closest proper rotation: U diag(1, 1, det(U V^T)) V^T
            U, _, Vh = np.linalg.svd(X[:, k].copy().reshape(3, 3))
            if np.linalg.det(U @ Vh) < 0:
                U[:, 2] = -U[:, 2]
            M = U @ Vh
            for i in range(3):
                for j in range(3):
                    X[3 * i + j, k] = M[i, j]


@njit(cache=True, nogil=True, inline="always")
def _rotmat_to_quat(r00, r01, r02, r10, r11, r12, r20, r21, r22) -> tuple[int, float, float, float, float, float]:
    """The quaternion (wxyz, w >= 0) of the rotation R (row-major entries), from the row of 4 q q^T with the largest
    diagonal entry: (row taken, s, w, x, y, z), with s the signed factor of q = s v (v that row, s = +-1 / |v|),
    which the backward needs."""
    v0 = 1.0 + r00 + r11 + r22
    v1 = 1.0 + r00 - r11 - r22
    v2 = 1.0 - r00 + r11 - r22
    v3 = 1.0 - r00 - r11 + r22
    wx, wy, wz = r21 - r12, r02 - r20, r10 - r01
    xy, xz, yz = r10 + r01, r02 + r20, r12 + r21
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
    return best, s, a * s, b * s, c * s, d * s


@njit(cache=True, nogil=True, inline="always")
def _unit_quat(quats, n) -> tuple[float, float, float, float, float]:
    """(w, x, y, z, |q|) of quats[n] normalised; one below NORM_EPS is the identity (framework.geometry's rule)."""
    w, qx, qy, qz = quats[n, 0], quats[n, 1], quats[n, 2], quats[n, 3]
    qn = math.sqrt(max(w * w + qx * qx + qy * qy + qz * qz, NORM_EPS * NORM_EPS))
    if qn > NORM_EPS:
        return w / qn, qx / qn, qy / qn, qz / qn, qn
    return 1.0, 0.0, 0.0, 0.0, qn


@njit(cache=True, nogil=True, inline="always")
def _axes(w, qx, qy, qz) -> tuple[float, float, float, float, float, float, float, float, float]:
    """The rotation of the unit quaternion wxyz, row-major: its columns are the Gaussian's axes a_l."""
    return (
        1 - 2 * (qy * qy + qz * qz),
        2 * (qx * qy - w * qz),
        2 * (qx * qz + w * qy),
        2 * (qx * qy + w * qz),
        1 - 2 * (qx * qx + qz * qz),
        2 * (qy * qz - w * qx),
        2 * (qx * qz - w * qy),
        2 * (qy * qz + w * qx),
        1 - 2 * (qx * qx + qy * qy),
    )


@njit(cache=True, nogil=True, inline="always")
def _rt_a(
    r00, r01, r02, r10, r11, r12, r20, r21, r22, a00, a01, a02, a10, a11, a12, a20, a21, a22
) -> tuple[float, float, float, float, float, float, float, float, float]:
    """R^T A, row-major, from the row-major entries of R and A."""
    # fmt: off
    return (r00 * a00 + r10 * a10 + r20 * a20, r00 * a01 + r10 * a11 + r20 * a21, r00 * a02 + r10 * a12 + r20 * a22,
            r01 * a00 + r11 * a10 + r21 * a20, r01 * a01 + r11 * a11 + r21 * a21, r01 * a02 + r11 * a12 + r21 * a22,
            r02 * a00 + r12 * a10 + r22 * a20, r02 * a01 + r12 * a11 + r22 * a21, r02 * a02 + r12 * a12 + r22 * a22)
    # fmt: on


@njit(cache=True, nogil=True)
def _rt_a_into(R, A, M) -> None:
    """M = R^T A for [3, 3] arrays (`_rt_a`)."""
    M[0, 0], M[0, 1], M[0, 2], M[1, 0], M[1, 1], M[1, 2], M[2, 0], M[2, 1], M[2, 2] = _rt_a(
        R[0, 0],
        R[0, 1],
        R[0, 2],
        R[1, 0],
        R[1, 1],
        R[1, 2],
        R[2, 0],
        R[2, 1],
        R[2, 2],
        A[0, 0],
        A[0, 1],
        A[0, 2],
        A[1, 0],
        A[1, 1],
        A[1, 2],
        A[2, 0],
        A[2, 1],
        A[2, 2],
    )


@njit(cache=True, nogil=True, inline="always")
def _quadratic_form(c0, c1, c2, m00, m01, m02, m10, m11, m12, m20, m21, m22) -> float:
    """c^T M c (row-major entries of M), summed row by row."""
    k = 0.0
    k += c0 * (m00 * c0 + m01 * c1 + m02 * c2)
    k += c1 * (m10 * c0 + m11 * c1 + m12 * c2)
    k += c2 * (m20 * c0 + m21 * c1 + m22 * c2)
    return k


@njit(cache=True, nogil=True, inline="always")
def _stretch(
    q00, q01, q02, q10, q11, q12, q20, q21, q22, m00, m01, m02, m10, m11, m12, m20, m21, m22
) -> tuple[float, float, float]:
    """k_l = a_l^T M a_l for the columns a_l of Q (row-major entries of Q and M)."""
    return (
        _quadratic_form(q00, q10, q20, m00, m01, m02, m10, m11, m12, m20, m21, m22),
        _quadratic_form(q01, q11, q21, m00, m01, m02, m10, m11, m12, m20, m21, m22),
        _quadratic_form(q02, q12, q22, m00, m01, m02, m10, m11, m12, m20, m21, m22),
    )


@njit(cache=True, nogil=True, inline="always")  # a call passing its nine arrays cost as much as the work
def _pose_lane(
    n,
    k,
    A9,
    t3,
    X,
    means,
    quats,
    log_scales,
    blended_centres,
    diag_stretch,
    out_means,
    out_quats,
    out_log_scales,
    out_rotations,
) -> None:
    """Pose Gaussian n from its blended affine part (A9[:, n], t3[:, n]) and A's rotation factor X[:, k]. On scalars:
    copied into 3x3 arrays, the same arithmetic took 2.3x as long (every entry went through memory)."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = (
        X[0, k],
        X[1, k],
        X[2, k],
        X[3, k],
        X[4, k],
        X[5, k],
        X[6, k],
        X[7, k],
        X[8, k],
    )
    a00, a01, a02, a10, a11, a12, a20, a21, a22 = (
        A9[0, n],
        A9[1, n],
        A9[2, n],
        A9[3, n],
        A9[4, n],
        A9[5, n],
        A9[6, n],
        A9[7, n],
        A9[8, n],
    )
    _, _, aw, ax, ay, az = _rotmat_to_quat(r00, r01, r02, r10, r11, r12, r20, r21, r22)
    x0, x1, x2 = means[n, 0], means[n, 1], means[n, 2]
    if blended_centres:
        out_means[n, 0] = a00 * x0 + a01 * x1 + a02 * x2 + t3[0, n]
        out_means[n, 1] = a10 * x0 + a11 * x1 + a12 * x2 + t3[1, n]
        out_means[n, 2] = a20 * x0 + a21 * x1 + a22 * x2 + t3[2, n]
    else:
        out_means[n, 0] = r00 * x0 + r01 * x1 + r02 * x2 + t3[0, n]
        out_means[n, 1] = r10 * x0 + r11 * x1 + r12 * x2 + t3[1, n]
        out_means[n, 2] = r20 * x0 + r21 * x1 + r22 * x2 + t3[2, n]
    w, qx, qy, qz, _ = _unit_quat(quats, n)
    out_quats[n, 0] = aw * w - ax * qx - ay * qy - az * qz
    out_quats[n, 1] = aw * qx + ax * w + ay * qz - az * qy
    out_quats[n, 2] = aw * qy - ax * qz + ay * w + az * qx
    out_quats[n, 3] = aw * qz + ax * qy - ay * qx + az * w
    out_rotations[n, 0, 0], out_rotations[n, 0, 1], out_rotations[n, 0, 2] = r00, r01, r02
    out_rotations[n, 1, 0], out_rotations[n, 1, 1], out_rotations[n, 1, 2] = r10, r11, r12
    out_rotations[n, 2, 0], out_rotations[n, 2, 1], out_rotations[n, 2, 2] = r20, r21, r22
    if not diag_stretch:
        for l in range(3):  # noqa: E741
            out_log_scales[n, l] = log_scales[n, l]
        return
    # the Gaussian's axes a_l (columns of its rotation) and k_l = a_l^T (R^T A) a_l
    q00, q01, q02, q10, q11, q12, q20, q21, q22 = _axes(w, qx, qy, qz)
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = _rt_a(
        r00, r01, r02, r10, r11, r12, r20, r21, r22, a00, a01, a02, a10, a11, a12, a20, a21, a22
    )
    k0, k1, k2 = _stretch(q00, q01, q02, q10, q11, q12, q20, q21, q22, m00, m01, m02, m10, m11, m12, m20, m21, m22)
    out_log_scales[n, 0] = log_scales[n, 0] + math.log(max(k0, LBS_MIN_STRETCH))
    out_log_scales[n, 1] = log_scales[n, 1] + math.log(max(k1, LBS_MIN_STRETCH))
    out_log_scales[n, 2] = log_scales[n, 2] + math.log(max(k2, LBS_MIN_STRETCH))


@njit(cache=True, nogil=True)
def blend_skipping_zeros(weights, transforms, A9, t3) -> None:
    """A9 [9, N], t3 [3, N] = the blend sum_k w_k P_k of weights [N, J] and transforms [J, 12] (rows of each bone's
    [3, 4]) over the non-zero weights only: a non-finite bone transform then reaches only the Gaussians it weights,
    where a matrix product spreads NaN * 0 to all of them."""
    N, J = weights.shape
    P = np.empty(12)
    for n in range(N):
        P[:] = 0.0
        for k in range(J):
            w = weights[n, k]
            if w != 0.0:
                for e in range(12):
                    P[e] += w * transforms[k, e]
        for i in range(3):
            for j in range(3):
                A9[3 * i + j, n] = P[4 * i + j]
            t3[i, n] = P[4 * i + 3]


@njit(cache=True, nogil=True)
def skin_affine_forward(
    A9,
    t3,
    means,
    quats,
    log_scales,
    blended_centres,
    diag_stretch,
    start,
    stop,
    out_means,
    out_quats,
    out_log_scales,
    out_rotations,
) -> None:
    """Pose Gaussians [start, stop) from their blended affine parts A9 [9, N] and t3 [3, N] (entry-major, as
    `framework.rig.lbs.blended_affine` gives them): means [N, 3], quats [N, 4] (wxyz, any norm), log_scales [N, 3]
    -> out_means [N, 3], out_quats [N, 4], out_log_scales [N, 3] and the rotations out_rotations [N, 3, 3] (the SH
    frames). The polar decomposition runs a block of Gaussians at a time (`_polar_block`), the rest per Gaussian."""
    X = np.empty((9, _BLOCK))
    state = np.empty(_BLOCK, np.int8)
    for first in range(start, stop, _BLOCK):
        last = min(first + _BLOCK, stop)
        _polar_block(A9, first, last, X, state)
        for n in range(first, last):
            _pose_lane(
                n,
                n - first,
                A9,
                t3,
                X,
                means,
                quats,
                log_scales,
                blended_centres,
                diag_stretch,
                out_means,
                out_quats,
                out_log_scales,
                out_rotations,
            )


@njit(cache=True, nogil=True)
def _polar_backward(A, R, G, out) -> None:
    """out = dL/dA of R = polar(A) for dL/dR = G (`framework.rig.polar._PolarRotation.backward`, per matrix): with
    S = sym(R^T A) and B = tr(S) I - S, h solves (B B + d^2 I) h = B vee(skew(R^T G)) (Tikhonov-damped), and
    dL/dA = R skew(h); entries that are not finite are 0."""
    S = np.empty((3, 3))
    _rt_a_into(R, A, S)
    W = np.empty((3, 3))
    _rt_a_into(R, G, W)
    g0, g1, g2 = W[2, 1] - W[1, 2], W[0, 2] - W[2, 0], W[1, 0] - W[0, 1]
    tr = S[0, 0] + S[1, 1] + S[2, 2]
    B = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            B[i, j] = (tr if i == j else 0.0) - 0.5 * (S[i, j] + S[j, i])
    d2 = (POLAR_TIKHONOV * abs(tr)) ** 2 + POLAR_DAMPING_FLOOR
    M = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            M[i, j] = B[i, 0] * B[0, j] + B[i, 1] * B[1, j] + B[i, 2] * B[2, j] + (d2 if i == j else 0.0)
    b0 = B[0, 0] * g0 + B[0, 1] * g1 + B[0, 2] * g2
    b1 = B[1, 0] * g0 + B[1, 1] * g1 + B[1, 2] * g2
    b2 = B[2, 0] * g0 + B[2, 1] * g1 + B[2, 2] * g2
    # M^-1 b by the adjugate of the symmetric M (framework.rig.polar._solve_sym3)
    m00, m01, m02, m11, m12, m22 = M[0, 0], M[0, 1], M[0, 2], M[1, 1], M[1, 2], M[2, 2]
    c00, c01, c02 = m11 * m22 - m12 * m12, m02 * m12 - m01 * m22, m01 * m12 - m02 * m11
    c11, c12, c22 = m00 * m22 - m02 * m02, m01 * m02 - m00 * m12, m00 * m11 - m01 * m01
    det = m00 * c00 + m01 * c01 + m02 * c02
    h0 = (c00 * b0 + c01 * b1 + c02 * b2) / det
    h1 = (c01 * b0 + c11 * b1 + c12 * b2) / det
    h2 = (c02 * b0 + c12 * b1 + c22 * b2) / det
    for i in range(3):  # R skew(h), skew(h) = [[0, -h2, h1], [h2, 0, -h0], [-h1, h0, 0]]
        e0 = R[i, 1] * h2 - R[i, 2] * h1
        e1 = R[i, 2] * h0 - R[i, 0] * h2
        e2 = R[i, 0] * h1 - R[i, 1] * h0
        out[i, 0] = e0 if math.isfinite(e0) else 0.0
        out[i, 1] = e1 if math.isfinite(e1) else 0.0
        out[i, 2] = e2 if math.isfinite(e2) else 0.0


@njit(cache=True, nogil=True)
def skin_affine_backward(
    A9,
    means,
    quats,
    rotations,
    blended_centres,
    diag_stretch,
    g_means,
    g_quats,
    g_log_scales,
    g_rotations,
    start,
    stop,
    grad_A9,
    grad_means,
    grad_quats,
) -> None:
    """The gradients of `skin_affine_forward`'s outputs (g_*) carried back to A9 [9, N], means [N, 3] and quats
    [N, 4], for Gaussians [start, stop); `rotations` [N, 3, 3] are the forward's R. (The translation's gradient is
    g_means itself, the log-scales' is g_log_scales: the wrapper passes those on.)"""
    A, R, Q, M = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    gA, gR, gQ, gM, polar = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    for n in range(start, stop):
        for i in range(3):
            for j in range(3):
                A[i, j] = A9[3 * i + j, n]
                R[i, j] = rotations[n, i, j]
                gR[i, j] = g_rotations[n, i, j]
                gA[i, j] = 0.0
        best, s, aw, ax, ay, az = _rotmat_to_quat(
            R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2], R[2, 0], R[2, 1], R[2, 2]
        )
        w, qx, qy, qz, qnorm = _unit_quat(quats, n)
        # centres: A x + t (or R x + t)
        x0, x1, x2 = means[n, 0], means[n, 1], means[n, 2]
        m = A if blended_centres else R
        gmov = gA if blended_centres else gR
        gm0, gm1, gm2 = g_means[n, 0], g_means[n, 1], g_means[n, 2]
        for j in range(3):
            grad_means[n, j] = m[0, j] * gm0 + m[1, j] * gm1 + m[2, j] * gm2
        for i, gi in ((0, gm0), (1, gm1), (2, gm2)):
            gmov[i, 0] += gi * x0
            gmov[i, 1] += gi * x1
            gmov[i, 2] += gi * x2
        # quaternions: qR * q_unit
        g0, g1, g2, g3 = g_quats[n, 0], g_quats[n, 1], g_quats[n, 2], g_quats[n, 3]
        ga0 = g0 * w + g1 * qx + g2 * qy + g3 * qz
        ga1 = -g0 * qx + g1 * w - g2 * qz + g3 * qy
        ga2 = -g0 * qy + g1 * qz + g2 * w - g3 * qx
        ga3 = -g0 * qz - g1 * qy + g2 * qx + g3 * w
        gu0 = g0 * aw + g1 * ax + g2 * ay + g3 * az
        gu1 = -g0 * ax + g1 * aw + g2 * az - g3 * ay
        gu2 = -g0 * ay - g1 * az + g2 * aw + g3 * ax
        gu3 = -g0 * az + g1 * ay - g2 * ax + g3 * aw
        if diag_stretch:
            # k_l = a_l^T M a_l with M = R^T A; log k_l clamped below at LBS_MIN_STRETCH (no gradient there)
            Q[0, 0], Q[0, 1], Q[0, 2], Q[1, 0], Q[1, 1], Q[1, 2], Q[2, 0], Q[2, 1], Q[2, 2] = _axes(w, qx, qy, qz)
            _rt_a_into(R, A, M)
            for i in range(3):
                for j in range(3):
                    gM[i, j] = 0.0
                    gQ[i, j] = 0.0
            ks = _stretch(
                Q[0, 0],
                Q[0, 1],
                Q[0, 2],
                Q[1, 0],
                Q[1, 1],
                Q[1, 2],
                Q[2, 0],
                Q[2, 1],
                Q[2, 2],
                M[0, 0],
                M[0, 1],
                M[0, 2],
                M[1, 0],
                M[1, 1],
                M[1, 2],
                M[2, 0],
                M[2, 1],
                M[2, 2],
            )
            for l in range(3):  # noqa: E741
                k = ks[l]
                gk = g_log_scales[n, l] / k if k >= LBS_MIN_STRETCH else 0.0
                for i in range(3):
                    for j in range(3):
                        gM[i, j] += gk * Q[i, l] * Q[j, l]
                    gQ[i, l] += gk * (
                        M[i, 0] * Q[0, l]
                        + M[i, 1] * Q[1, l]
                        + M[i, 2] * Q[2, l]
                        + M[0, i] * Q[0, l]
                        + M[1, i] * Q[1, l]
                        + M[2, i] * Q[2, l]
                    )
            for a in range(3):
                for b in range(3):
                    gR[a, b] += A[a, 0] * gM[b, 0] + A[a, 1] * gM[b, 1] + A[a, 2] * gM[b, 2]  # A gM^T
                    gA[a, b] += R[a, 0] * gM[0, b] + R[a, 1] * gM[1, b] + R[a, 2] * gM[2, b]  # R gM
            # through Q = rot(q_unit) (framework.geometry._QuatToRotmat.backward)
            s01, s02, s12 = gQ[0, 1] + gQ[1, 0], gQ[0, 2] + gQ[2, 0], gQ[1, 2] + gQ[2, 1]
            a01, a02, a12 = gQ[1, 0] - gQ[0, 1], gQ[0, 2] - gQ[2, 0], gQ[2, 1] - gQ[1, 2]
            gu0 += 2 * (qz * a01 + qy * a02 + qx * a12)
            gu1 += 2 * (qy * s01 + qz * s02 + w * a12 - 2 * qx * (gQ[1, 1] + gQ[2, 2]))
            gu2 += 2 * (qx * s01 + w * a02 + qz * s12 - 2 * qy * (gQ[0, 0] + gQ[2, 2]))
            gu3 += 2 * (w * a01 + qx * s02 + qy * s12 - 2 * qz * (gQ[0, 0] + gQ[1, 1]))
        # through q / |q| (radial part removed; a quaternion below NORM_EPS is the constant identity)
        if qnorm > NORM_EPS:
            dot = w * gu0 + qx * gu1 + qy * gu2 + qz * gu3
            grad_quats[n, 0] = (gu0 - w * dot) / qnorm
            grad_quats[n, 1] = (gu1 - qx * dot) / qnorm
            grad_quats[n, 2] = (gu2 - qy * dot) / qnorm
            grad_quats[n, 3] = (gu3 - qz * dot) / qnorm
        else:
            grad_quats[n, 0] = grad_quats[n, 1] = grad_quats[n, 2] = grad_quats[n, 3] = 0.0
        # through qR = s v (v the chosen row of 4 q q^T, linear in R; s = +-1 / |v|)
        dot = aw * ga0 + ax * ga1 + ay * ga2 + az * ga3
        gv0, gv1, gv2, gv3 = s * (ga0 - aw * dot), s * (ga1 - ax * dot), s * (ga2 - ay * dot), s * (ga3 - az * dot)
        gd0 = gd1 = gd2 = gd3 = gwx = gwy = gwz = gxy = gxz = gyz = 0.0
        if best == 0:
            gd0, gwx, gwy, gwz = gv0, gv1, gv2, gv3
        elif best == 1:
            gwx, gd1, gxy, gxz = gv0, gv1, gv2, gv3
        elif best == 2:
            gwy, gxy, gd2, gyz = gv0, gv1, gv2, gv3
        else:
            gwz, gxz, gyz, gd3 = gv0, gv1, gv2, gv3
        gR[0, 0] += gd0 + gd1 - gd2 - gd3
        gR[1, 1] += gd0 - gd1 + gd2 - gd3
        gR[2, 2] += gd0 - gd1 - gd2 + gd3
        gR[2, 1] += gwx + gyz
        gR[1, 2] += gyz - gwx
        gR[0, 2] += gwy + gxz
        gR[2, 0] += gxz - gwy
        gR[1, 0] += gwz + gxy
        gR[0, 1] += gxy - gwz
        # through R = polar(A)
        _polar_backward(A, R, gR, polar)
        for i in range(3):
            for j in range(3):
                grad_A9[3 * i + j, n] = gA[i, j] + polar[i, j]


class _SkinAffine(torch.autograd.Function):
    """(A9 [9, N], t3 [3, N], means [N, 3], quats [N, 4], log_scales [N, 3]) -> (means', quats', log_scales' [N, 3],
    R [N, 3, 3]), differentiable in the five inputs; float64 inside, results in the inputs' dtype."""

    @staticmethod
    def forward(ctx, A9, t3, means, quats, log_scales, blended: bool, diag: bool):  # type: ignore[override]
        from framework.kernels.rasterize import float64_array as f64

        N, dtype = means.shape[0], means.dtype
        a9, m64, q64 = f64(A9), f64(means), f64(quats)
        out = (np.empty((N, 3)), np.empty((N, 4)), np.empty((N, 3)), np.empty((N, 3, 3)))
        run_chunked(skin_affine_forward, (a9, f64(t3), m64, q64, f64(log_scales), blended, diag), out, N)
        ctx.arrays = (a9, m64, q64, out[3])  # numpy: the forward's float64 copies and R, for the backward
        ctx.flags, ctx.dtype = (blended, diag), dtype
        return tuple(torch.from_numpy(o).to(dtype) for o in out)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_means, g_quats, g_log_scales, g_rotations):  # type: ignore[override]
        from framework.kernels.rasterize import float64_array as f64

        a9, m64, q64, r64 = ctx.arrays
        N, dtype = m64.shape[0], ctx.dtype
        zeros = torch.zeros
        g_m = f64(g_means) if g_means is not None else np.zeros((N, 3))
        g_q = f64(g_quats) if g_quats is not None else np.zeros((N, 4))
        g_ls = g_log_scales if g_log_scales is not None else zeros(N, 3, dtype=dtype)
        g_r = f64(g_rotations) if g_rotations is not None else np.zeros((N, 3, 3))
        out = (np.empty((9, N)), np.empty((N, 3)), np.empty((N, 4)))
        run_chunked(skin_affine_backward, (a9, m64, q64, r64, *ctx.flags, g_m, g_q, f64(g_ls), g_r), out, N)
        big = torch.finfo(dtype).max  # a float32 result saturates rather than overflowing to inf
        grad_A9 = torch.from_numpy(out[0]).clamp(-big, big).to(dtype)
        grad_t3 = torch.from_numpy(g_m).t().to(dtype)
        grads = (grad_A9, grad_t3, torch.from_numpy(out[1]).to(dtype), torch.from_numpy(out[2]).to(dtype), g_ls)
        return (*grads, None, None)


def lbs_with_sh_frames_trainable(gaussians, weights, transforms, stretch: str = "diag", centres: str = "blended"):
    """`framework.rig.lbs.lbs_with_sh_frames` with gradients, the per-Gaussian part compiled: the blend (one matrix
    product, `blended_affine`) stays in torch, the polar decomposition, quaternions, centres and stretch run in
    `skin_affine_forward` and their gradients in `skin_affine_backward`, on every thread. CPU tensors only."""
    from framework.rig.lbs import blended_affine

    A, t = blended_affine(weights, transforms)  # [3, 3, N], [3, N]
    N = A.shape[-1]
    means, quats, log_scales, R = _SkinAffine.apply(
        A.reshape(9, N),
        t,
        gaussians.means,
        gaussians.quats,
        gaussians.log_scales,
        centres == "blended",
        stretch == "diag",
    )
    return gaussians.replace(means=means, quats=quats, log_scales=log_scales), R


def lbs_with_sh_frames_compiled(gaussians, weights, transforms, stretch: str = "diag", centres: str = "blended"):
    """`framework.rig.lbs.lbs_with_sh_frames` (posed Gaussians with canonical SH, R [N, 3, 3]) through
    `skin_affine_forward`: no gradients, CPU tensors; results in the Gaussians' dtype.

    The blend is one float64 matrix product when every bone transform is finite (faster than the loop), and
    `blend_skipping_zeros` otherwise (module docstring)."""
    from framework.kernels.rasterize import float64_array as f64
    from framework.rig.lbs import blended_affine

    N, dtype = gaussians.means.shape[0], gaussians.means.dtype
    if bool(torch.isfinite(transforms).all()):
        A, t = blended_affine(weights.to(torch.float64), transforms.to(torch.float64))  # [3, 3, N], [3, N]
        A9, t3 = f64(A.reshape(9, N)), f64(t)
    else:
        A9, t3 = np.empty((9, N)), np.empty((3, N))
        blend_skipping_zeros(f64(weights), f64(transforms[:, :3, :].reshape(-1, 12)), A9, t3)
    out_means, out_quats, out_log_scales = np.empty((N, 3)), np.empty((N, 4)), np.empty((N, 3))
    out_rotations = np.empty((N, 3, 3))
    skin_affine_forward(
        A9,
        t3,
        f64(gaussians.means),
        f64(gaussians.quats),
        f64(gaussians.log_scales),
        centres == "blended",
        stretch == "diag",
        0,
        N,
        out_means,
        out_quats,
        out_log_scales,
        out_rotations,
    )
    posed = gaussians.replace(
        means=torch.from_numpy(out_means).to(dtype),
        quats=torch.from_numpy(out_quats).to(dtype),
        log_scales=torch.from_numpy(out_log_scales).to(dtype),
    )
    return posed, torch.from_numpy(out_rotations).to(dtype)
