"""The rasterizer contract as compiled loops (numba): projection and front-to-back compositing, and their backward.

Why: at the resolutions a CPU renders in real time (128-512 px) the eager `torch_ref` frame is mostly per-operation
overhead. Its projection alone is about 300 small tensor operations and its compositor about a thousand, each a few
microseconds, however few Gaussians there are (`tools/bench_render.py --scaling` measures that fixed cost). A loop
compiled once does the same arithmetic without that overhead. It also needs no pair list, no sort and no per-pair
buffers: the entries are visited in depth order, and each visit updates the transmittance and the sums of the pixels its
footprint covers. That is front-to-back compositing pixel by pixel, as the contract (`framework.interfaces.rasterizer`)
defines it, because a pixel sees its entries in the same order either way.

Training renders use the same loops with hand-written backward passes (`project_backward`, `accumulate_backward`;
the autograd Functions are `framework.kernels.projection` and `framework.kernels.compositing`).
Everything is computed in float64 and the results are cast to the caller's dtype.
A float32 render therefore differs from `torch_ref`'s float32 render by float32 rounding, and both differ from a float64
render by about the same amount; `tests/test_numba_rasterizer.py` checks that against `torch_ref` in float64. The pairs
each entry visits are the ones `framework.splat.pairs.enumerate_pairs` lists: the rows of its screen box, and in each
row the exact span of the ellipse where alpha can reach 1/255, widened by BOX_MARGIN.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit

from framework.splat.contract import ALPHA_MAX, ALPHA_MIN, BOX_MARGIN, TRANSMITTANCE_MIN
from framework.splat.projection import EXTEND_MAX, FOV_MARGIN

_BIG = float(2**30)  # the projection's cap on a half extent (as `framework.splat.projection`)
_NO_LOG = (np.empty(0, dtype=np.int32), np.empty(0, dtype=np.int32), np.empty(0))  # `accumulate` without a pair log
_TINY = 1.1754943508222875e-38  # float32's smallest normal: the conic's a is clamped to it before dividing


def float64_array(t: torch.Tensor) -> np.ndarray:
    """A CPU tensor as the contiguous float64 array the compiled loops read (a copy unless it already is one)."""
    return t.detach().to(torch.float64).contiguous().numpy()


@njit(cache=True, nogil=True)
def _clamp_index(v: float, lo: int, hi: int) -> int:
    """Clamp in floating point, then convert (NaN -> lo): a huge coordinate must not overflow the integer."""
    if not v >= lo:
        return lo
    if v > hi:
        return hi
    return int(v)


@njit(cache=True, nogil=True)
def _view_limits(K, c, width, height):
    """Camera c's fx, fy, cx, cy and the limits of x/z, y/z in its field of view widened by FOV_MARGIN (3DGS)."""
    fx, fy, cx, cy = K[c, 0, 0], K[c, 1, 1], K[c, 0, 2], K[c, 1, 2]
    u_lo, v_lo = -(cx + 0.5 * FOV_MARGIN * width) / fx, -(cy + 0.5 * FOV_MARGIN * height) / fy
    u_hi, v_hi = ((1.0 + 0.5 * FOV_MARGIN) * width - cx) / fx, ((1.0 + 0.5 * FOV_MARGIN) * height - cy) / fy
    return fx, fy, cx, cy, u_lo, v_lo, u_hi, v_hi


@njit(cache=True, nogil=True)
def _to_camera(world_to_cam, c, means, n):
    """Gaussian n's centre in camera c's frame: (x, y, z)."""
    m0, m1, m2 = means[n, 0], means[n, 1], means[n, 2]
    w = world_to_cam[c]
    x = w[0, 0] * m0 + w[0, 1] * m1 + w[0, 2] * m2 + w[0, 3]
    y = w[1, 0] * m0 + w[1, 1] * m1 + w[1, 2] * m2 + w[1, 3]
    z = w[2, 0] * m0 + w[2, 1] * m1 + w[2, 2] * m2 + w[2, 3]
    return x, y, z


@njit(cache=True, nogil=True)
def _unit_rotation(quats, n, rot):
    """Writes the rotation of Gaussian n's normalised quaternion into rot [3, 3]; returns (w, x, y, z, |q|, unit).

    A norm <= 1e-12 counts as the identity (`framework.guards.NORM_EPS`), with `unit` False: a constant."""
    w, qx, qy, qz = quats[n, 0], quats[n, 1], quats[n, 2], quats[n, 3]
    qn = math.sqrt(max(w * w + qx * qx + qy * qy + qz * qz, 1e-24))
    unit = qn > 1e-12
    if unit:
        w, qx, qy, qz = w / qn, qx / qn, qy / qn, qz / qn
    else:
        w, qx, qy, qz = 1.0, 0.0, 0.0, 0.0
    rot[0, 0], rot[0, 1], rot[0, 2] = 1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - w * qz), 2 * (qx * qz + w * qy)
    rot[1, 0], rot[1, 1], rot[1, 2] = 2 * (qx * qy + w * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - w * qx)
    rot[2, 0], rot[2, 1], rot[2, 2] = 2 * (qx * qz - w * qy), 2 * (qy * qz + w * qx), 1 - 2 * (qx * qx + qy * qy)
    return w, qx, qy, qz, qn, unit


@njit(cache=True, nogil=True)
def _screen_covariance(Rc, rot, scales, n, uc, vc, a0, a1, eps2d, wm, t0, t1):
    """The dilated 2D covariance of Gaussian n: writes W R S into wm [3, 3] (row i: camera axis i) and the rows of
    T = J W R S into t0, t1 [3] (J at the clamped uc, vc; a0 = fx / z, a1 = fy / z); returns (cxx, cxy, cyy, k0, k1,
    k2, det) with k = T0 x T1 and det = |k|^2 + eps2d (cxx + cyy - eps2d), Lagrange's identity, as the projection."""
    for j in range(3):
        s = scales[n, j]
        for i in range(3):
            wm[i, j] = (Rc[i, 0] * rot[0, j] + Rc[i, 1] * rot[1, j] + Rc[i, 2] * rot[2, j]) * s
        t0[j] = (wm[0, j] - uc * wm[2, j]) * a0
        t1[j] = (wm[1, j] - vc * wm[2, j]) * a1
    cxx = t0[0] * t0[0] + t0[1] * t0[1] + t0[2] * t0[2] + eps2d
    cxy = t0[0] * t1[0] + t0[1] * t1[1] + t0[2] * t1[2]
    cyy = t1[0] * t1[0] + t1[1] * t1[1] + t1[2] * t1[2] + eps2d
    k0 = t0[1] * t1[2] - t0[2] * t1[1]
    k1 = t0[2] * t1[0] - t0[0] * t1[2]
    k2 = t0[0] * t1[1] - t0[1] * t1[0]
    det = k0 * k0 + k1 * k1 + k2 * k2 + eps2d * (cxx + cyy - eps2d)
    return cxx, cxy, cyy, k0, k1, k2, det


@njit(cache=True, nogil=True)
def project(
    means,
    quats,
    scales,
    opacities,
    K,
    world_to_cam,
    width,
    height,
    near,
    far,
    eps2d,
    means2d,
    conics,
    depths,
    half,
    radii,
    valid,
    cov2d,
):
    """EWA projection of N Gaussians into C cameras, the rules of `framework.splat.projection.project_gaussians`.

    In: means [N, 3], quats [N, 4] (wxyz, any norm), scales [N, 3], opacities [N], K [C, 3, 3], world_to_cam
    [C, 4, 4]. Out (written): means2d [C, N, 2], conics [C, N, 3], depths [C, N], half [C, N, 2] (0 where culled),
    radii [C, N] (0 where culled), valid [C, N], cov2d [C, N, 3] (the dilated Sigma2d's xx, xy, yy)."""
    C, N = K.shape[0], means.shape[0]
    extend = np.empty(N)
    rs, wm = np.empty((3, 3)), np.empty((3, 3))  # scratch, reused per entry (an allocation each costs more than
    t0, t1 = np.empty(3), np.empty(3)  # its arithmetic)
    for n in range(N):
        extend[n] = min(math.sqrt(2.0 * math.log(max(opacities[n] / ALPHA_MIN, 1.0))), EXTEND_MAX)
    for c in range(C):
        fx, fy, cx, cy, u_lo, v_lo, u_hi, v_hi = _view_limits(K, c, width, height)
        Rc = world_to_cam[c, :3, :3]
        for n in range(N):
            x, y, z = _to_camera(world_to_cam, c, means, n)
            in_depth = z > near and z < far
            rz = 1.0 / z if in_depth else 1.0
            u, v = x * rz, y * rz
            mx, my = cx + fx * u, cy + fy * v
            _unit_rotation(quats, n, rs)  # then times the scales, column by column below
            uc, vc = min(max(u, u_lo), u_hi), min(max(v, v_lo), v_hi)
            cxx, cxy, cyy, _, _, _, det = _screen_covariance(
                Rc, rs, scales, n, uc, vc, fx * rz, fy * rz, eps2d, wm, t0, t1
            )
            ok_det = det > 0
            inv = 1.0 / det if ok_det else 1.0
            means2d[c, n, 0], means2d[c, n, 1] = mx, my
            cov2d[c, n, 0], cov2d[c, n, 1], cov2d[c, n, 2] = cxx, cxy, cyy
            conics[c, n, 0], conics[c, n, 1], conics[c, n, 2] = cyy * inv, -cxy * inv, cxx * inv
            depths[c, n] = z
            hx = math.sqrt(max(cxx, 0.0)) * extend[n]
            hy = math.sqrt(max(cyy, 0.0)) * extend[n]
            hx = 0.0 if math.isnan(hx) else min(hx, _BIG)
            hy = 0.0 if math.isnan(hy) else min(hy, _BIG)
            rx, ry = math.ceil(hx), math.ceil(hy)
            inside = mx + rx > 0 and mx - rx < width and my + ry > 0 and my - ry < height
            finite = (
                math.isfinite(mx)
                and math.isfinite(my)
                and math.isfinite(cxx)
                and math.isfinite(cxy)
                and math.isfinite(cyy)
            )
            radius = max(rx, ry)
            ok = in_depth and ok_det and opacities[n] >= ALPHA_MIN and inside and finite and radius > 0
            valid[c, n] = ok
            radii[c, n] = int(radius) if ok else 0
            half[c, n, 0] = hx if ok else 0.0
            half[c, n, 1] = hy if ok else 0.0


@njit(cache=True, nogil=True)
def project_backward(
    means,
    quats,
    scales,
    K,
    world_to_cam,
    width,
    height,
    eps2d,
    valid,
    g_means2d,
    g_conics,
    g_depths,
    g_means,
    g_quats,
    g_scales,
):
    """The gradients of `project`'s means2d, conics and depths with respect to means, quats and scales.

    In: the forward's inputs and its `valid` [C, N]; g_means2d [C, N, 2], g_conics [C, N, 3], g_depths [C, N]. Out
    (added to): g_means [N, 3], g_quats [N, 4], g_scales [N, 3]. Culled entries contribute nothing (their values
    are constants of the render). Per entry, the forward is recomputed and the chain rule applied step by step in
    reverse, the same derivatives autograd takes through `framework.splat.projection.project_gaussians`: the conic
    through the determinant in Lagrange's form, the Jacobian rows at the field-of-view clamp (whose slope is 0
    outside the widened view), the quaternion through its normalisation (zero below NORM_EPS)."""
    C, N = K.shape[0], means.shape[0]
    rot, wm, g_wm, g_rot = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))  # scratch per entry
    t0, t1, g_t0, g_t1 = np.empty(3), np.empty(3), np.empty(3), np.empty(3)  # (wm: W R S, row i = camera axis i)
    for c in range(C):
        fx, fy, cx, cy, u_lo, v_lo, u_hi, v_hi = _view_limits(K, c, width, height)
        Rc = world_to_cam[c, :3, :3]
        for n in range(N):
            if not valid[c, n]:
                continue
            x, y, z = _to_camera(world_to_cam, c, means, n)
            rz = 1.0 / z  # valid entries are inside the depth range
            u, v = x * rz, y * rz
            w, qx, qy, qz, qn, unit = _unit_rotation(quats, n, rot)
            uc, vc = min(max(u, u_lo), u_hi), min(max(v, v_lo), v_hi)
            a0, a1 = fx * rz, fy * rz
            cxx, cxy, cyy, k0, k1, k2, det = _screen_covariance(Rc, rot, scales, n, uc, vc, a0, a1, eps2d, wm, t0, t1)
            inv = 1.0 / det
            # conic = (cyy, -cxy, cxx) / det
            ga, gb, gc = g_conics[c, n, 0], g_conics[c, n, 1], g_conics[c, n, 2]
            g_det = -(ga * cyy - gb * cxy + gc * cxx) * inv * inv
            g_cxx = gc * inv + eps2d * g_det
            g_cyy = ga * inv + eps2d * g_det
            g_cxy = -gb * inv
            # d|T0 x T1|^2: T0 gets 2 (T1 x k), T1 gets 2 (k x T0)
            g_t0[0] = 2 * g_det * (t1[1] * k2 - t1[2] * k1) + 2 * g_cxx * t0[0] + g_cxy * t1[0]
            g_t0[1] = 2 * g_det * (t1[2] * k0 - t1[0] * k2) + 2 * g_cxx * t0[1] + g_cxy * t1[1]
            g_t0[2] = 2 * g_det * (t1[0] * k1 - t1[1] * k0) + 2 * g_cxx * t0[2] + g_cxy * t1[2]
            g_t1[0] = 2 * g_det * (k1 * t0[2] - k2 * t0[1]) + 2 * g_cyy * t1[0] + g_cxy * t0[0]
            g_t1[1] = 2 * g_det * (k2 * t0[0] - k0 * t0[2]) + 2 * g_cyy * t1[1] + g_cxy * t0[1]
            g_t1[2] = 2 * g_det * (k0 * t0[1] - k1 * t0[0]) + 2 * g_cyy * t1[2] + g_cxy * t0[2]
            # T0 = (W0 - uc W2) a0, T1 = (W1 - vc W2) a1
            g_uc = g_vc = g_a0 = g_a1 = 0.0
            for j in range(3):
                g_wm[0, j] = a0 * g_t0[j]
                g_wm[1, j] = a1 * g_t1[j]
                g_wm[2, j] = -uc * a0 * g_t0[j] - vc * a1 * g_t1[j]
                g_uc -= a0 * wm[2, j] * g_t0[j]
                g_vc -= a1 * wm[2, j] * g_t1[j]
                g_a0 += (wm[0, j] - uc * wm[2, j]) * g_t0[j]
                g_a1 += (wm[1, j] - vc * wm[2, j]) * g_t1[j]
            g_rz = fx * g_a0 + fy * g_a1
            g_u = fx * g_means2d[c, n, 0] + (g_uc if u_lo <= u <= u_hi else 0.0)
            g_v = fy * g_means2d[c, n, 1] + (g_vc if v_lo <= v <= v_hi else 0.0)
            g_rz += x * g_u + y * g_v
            g_x, g_y = rz * g_u, rz * g_v
            g_z = g_depths[c, n] - rz * rz * g_rz
            for i in range(3):
                g_means[n, i] += Rc[0, i] * g_x + Rc[1, i] * g_y + Rc[2, i] * g_z
            # W R S = Rc (rot S): d(rot S) = Rc^T dW; then rot and S
            for j in range(3):
                s = scales[n, j]
                g_s = 0.0
                for k in range(3):
                    g_m = Rc[0, k] * g_wm[0, j] + Rc[1, k] * g_wm[1, j] + Rc[2, k] * g_wm[2, j]
                    g_rot[k, j] = g_m * s
                    g_s += g_m * rot[k, j]
                g_scales[n, j] += g_s
            if not unit:
                continue  # the identity of a zero quaternion is a constant
            s01, s02, s12 = g_rot[0, 1] + g_rot[1, 0], g_rot[0, 2] + g_rot[2, 0], g_rot[1, 2] + g_rot[2, 1]
            d01, d02, d12 = g_rot[1, 0] - g_rot[0, 1], g_rot[0, 2] - g_rot[2, 0], g_rot[2, 1] - g_rot[1, 2]
            gw = 2 * (qz * d01 + qy * d02 + qx * d12)
            gx = 2 * (qy * s01 + qz * s02 + w * d12 - 2 * qx * (g_rot[1, 1] + g_rot[2, 2]))
            gy = 2 * (qx * s01 + w * d02 + qz * s12 - 2 * qy * (g_rot[0, 0] + g_rot[2, 2]))
            gz = 2 * (w * d01 + qx * s02 + qy * s12 - 2 * qz * (g_rot[0, 0] + g_rot[1, 1]))
            radial = w * gw + qx * gx + qy * gy + qz * gz  # through q / |q|: drop the radial part
            g_quats[n, 0] += (gw - w * radial) / qn
            g_quats[n, 1] += (gx - qx * radial) / qn
            g_quats[n, 2] += (gy - qy * radial) / qn
            g_quats[n, 3] += (gz - qz * radial) / qn


@njit(cache=True, nogil=True)
def _next_open(skip, i: int) -> int:
    """The first pixel at or after slot `i` of its row that is not finished (path halving keeps the chains short)."""
    while skip[i] != i:
        skip[i] = skip[skip[i]]
        i = skip[i]
    return i


@njit(cache=True, nogil=True)
def _row_span(mx, my, a, b, c, big_l, y, width):
    """Pixels [x0, x1] of row `y` where the entry's sigma <= L (alpha can reach 1/255), widened by BOX_MARGIN; empty
    (x0 > x1) where the row misses the ellipse. The same span as `framework.splat.pairs.enumerate_pairs`."""
    dy = my - (y + 0.5)
    disc = (b * dy) ** 2 - a * (c * dy * dy - 2.0 * big_l)  # sigma(dx) <= L is a quadratic in dx
    if not disc >= 0:
        return 0, -1
    sq = math.sqrt(disc)
    a_safe = max(a, _TINY)
    x0 = _clamp_index(math.ceil(mx - (-b * dy + sq) / a_safe - BOX_MARGIN - 0.5), 0, width)
    x1 = _clamp_index(math.floor(mx - (-b * dy - sq) / a_safe + BOX_MARGIN - 0.5), -1, width - 1)
    return x0, x1


@njit(cache=True, nogil=True)
def _row_range(my, half_y, height):
    """Rows [y0, y1] of an entry's screen box (widened by BOX_MARGIN), clamped to the image."""
    y0 = _clamp_index(math.ceil(my - half_y - BOX_MARGIN - 0.5), 0, height)
    y1 = _clamp_index(math.floor(my + half_y + BOX_MARGIN - 0.5), -1, height - 1)
    return y0, y1


@njit(cache=True, nogil=True)
def accumulate(
    order,
    base_row,
    means2d,
    conics,
    opacities,
    colors,
    depths,
    half,
    width,
    height,
    T,
    acc,
    log_slot,
    log_pos,
    log_alpha,
):
    """Front-to-back compositing of the entries `order` (indices, nearest first) into per-pixel sums.

    In: means2d [N, 2], conics [N, 3], opacities [N], colors [N, 3], depths [N], half [N, 2]; base_row [len(order)]
    the first row of each visited entry's image in the stacked rows (camera * height; 0 for one image). In/out, one
    slot per pixel and W + 1 slots per stacked row (the last is a row's end marker): T [rows * (W + 1)] the
    transmittance (start at 1), acc [rows * (W + 1), 4] the sums of T * alpha * (r, g, b, z).

    It logs the pairs that contributed, in the order they were added, for the backward to replay in reverse: their
    slot, position in `order` and alpha go to log_slot, log_pos, log_alpha [capacity] (size 0 for no log). It returns
    the number of pairs; where that exceeds the capacity the log is incomplete, and the caller runs it again with
    room for them all (a forward that does not branch on a growing log measured 2.3x faster at 10k Gaussians, 128²).
    Slots and positions are int32 (16 bytes a pair in all): 450k pairs for 10k random Gaussians at 128².

    A pixel is finished when the transmittance after a pair would fall to 1e-4; that pair is not added (the
    contract's early termination), and neither is any pair after it.

    Finished pixels are skipped without being visited: each row keeps, per slot, a link towards the next pixel that
    is still open (the slot W past the row's end is never finished), so a span costs its open pixels, not its width.
    Where the footprints pile up (opaque surfaces, large Gaussians) most pairs fall on finished pixels, so this more
    than halves a frame of large Gaussians.

    One thread: two threads on interleaved rows measured no faster (docs/results/speed.md)."""
    stride = width + 1
    skip = np.arange(T.shape[0])  # skip[i] == i: open (or the row's end slot); else a link further right
    capacity = log_slot.shape[0]
    count = 0
    for k in range(order.shape[0]):
        e = order[k]
        mx, my = means2d[e, 0], means2d[e, 1]
        a, b, c = conics[e, 0], conics[e, 1], conics[e, 2]
        op = opacities[e]
        big_l = math.log(max(op / ALPHA_MIN, 1.0))  # sigma <= L wherever alpha can reach 1/255
        y0, y1 = _row_range(my, half[e, 1], height)
        for y in range(y0, y1 + 1):
            x0, x1 = _row_span(mx, my, a, b, c, big_l, y, width)
            dy = my - (y + 0.5)
            row = (base_row[k] + y) * stride
            p = _next_open(skip, row + x0)
            while p <= row + x1:
                dx = mx - (p - row + 0.5)
                neg_sigma = (-0.5 * a * dx - b * dy) * dx - 0.5 * c * dy * dy
                raw = op * math.exp(neg_sigma)
                if neg_sigma <= 0 and raw >= ALPHA_MIN:
                    al = min(raw, ALPHA_MAX)
                    next_t = T[p] * (1.0 - al)
                    if next_t <= TRANSMITTANCE_MIN:
                        skip[p] = p + 1  # finished: later spans step over it
                    else:
                        wgt = T[p] * al
                        acc[p, 0] += wgt * colors[e, 0]
                        acc[p, 1] += wgt * colors[e, 1]
                        acc[p, 2] += wgt * colors[e, 2]
                        acc[p, 3] += wgt * depths[e]
                        T[p] = next_t
                        if count < capacity:
                            log_slot[count], log_pos[count], log_alpha[count] = p, k, al
                        count += 1
                p = _next_open(skip, p + 1)
    return count


@njit(cache=True, nogil=True)
def accumulate_backward(
    order,
    base_row,
    means2d,
    conics,
    opacities,
    colors,
    depths,
    width,
    T,
    log_slot,
    log_pos,
    log_alpha,
    g_acc,
    tail,
    g_means2d,
    g_conics,
    g_opacities,
    g_colors,
    g_depths,
):
    """The gradients of `accumulate`'s sums (and final transmittance) with respect to every entry, in closed form.

    In: the forward's entries and its pair log; T [slots] the final transmittance (overwritten: walked back to 1),
    g_acc [slots, 4] dL/d(r, g, b, z sums), tail [slots] T_final * dL/dT_final (overwritten). Out (added to):
    g_means2d [N, 2], g_conics [N, 3], g_opacities [N], g_colors [N, 3], g_depths [N].

    The log is replayed backwards, so every pixel sees its pairs back to front. At each pair, with w = T alpha and
    v = dL/d(sums) . (r, g, b, z) of the entry, the transmittance before it is T_after / (1 - alpha) (alpha <= 0.999,
    and every value is float64) and dL/dalpha = T v - B / (1 - alpha), where B, the effect of the pixel's later pairs
    and T_final, grows by w v (`torch_ref`'s closed form, walked per pixel instead of by a segmented sum). alpha =
    opacity exp(-sigma), so dL/dsigma = -alpha dL/dalpha: zero where alpha was clamped at 0.999. The log holds the
    pairs entry by entry, so the per-entry sums stay in registers until the entry changes."""
    stride = width + 1
    i = log_slot.shape[0] - 1
    while i >= 0:
        k = log_pos[i]
        e = order[k]
        mx, my = means2d[e, 0], means2d[e, 1]
        a, b, c = conics[e, 0], conics[e, 1], conics[e, 2]
        r, gr_, b_, z = colors[e, 0], colors[e, 1], colors[e, 2], depths[e]
        s_x = s_y = s_xx = s_xy = s_yy = s_g = 0.0  # sums of g dx, g dy, g dx², g dx dy, g dy², g; g = alpha dL/dalpha
        c_r = c_g = c_b = c_z = 0.0  # sums of w dL/d(sums)
        while i >= 0 and log_pos[i] == k:
            p, al = log_slot[i], log_alpha[i]
            i -= 1
            row = p // stride
            dx = mx - (p - row * stride + 0.5)
            dy = my - (row - base_row[k] + 0.5)
            keep = 1.0 / (1.0 - al)
            t_before = T[p] * keep
            g0, g1, g2, g3 = g_acc[p, 0], g_acc[p, 1], g_acc[p, 2], g_acc[p, 3]
            v = g0 * r + g1 * gr_ + g2 * b_ + g3 * z
            wgt = t_before * al
            c_r += wgt * g0
            c_g += wgt * g1
            c_b += wgt * g2
            c_z += wgt * g3
            if al < ALPHA_MAX:
                g = (t_before * v - tail[p] * keep) * al
                s_x += g * dx
                s_y += g * dy
                s_xx += g * dx * dx
                s_xy += g * dx * dy
                s_yy += g * dy * dy
                s_g += g
            tail[p] += wgt * v
            T[p] = t_before
        # sigma = a dx² / 2 + b dx dy + c dy² / 2 with d = mean2d - pixel centre, and dL/dsigma = -g
        g_means2d[e, 0] -= a * s_x + b * s_y
        g_means2d[e, 1] -= b * s_x + c * s_y
        g_conics[e, 0] -= 0.5 * s_xx
        g_conics[e, 1] -= s_xy
        g_conics[e, 2] -= 0.5 * s_yy
        g_opacities[e] += s_g / opacities[e]  # d alpha / d opacity = alpha / opacity
        g_colors[e, 0] += c_r
        g_colors[e, 1] += c_g
        g_colors[e, 2] += c_b
        g_depths[e] += c_z


def composite(order, means2d, conics, opacities, colors, depths, half, width, height, background, rgb, alpha, depth):
    """One camera's image from its entries `order` (indices, nearest first): `accumulate`, then the background.

    In: means2d [N, 2], conics [N, 3], opacities [N], colors [N, 3], depths [N], half [N, 2], background [3].
    Out (written, float32 or float64): rgb [H, W, 3], alpha [H, W], depth [H, W]."""
    stride = width + 1
    T = np.ones(height * stride)
    acc = np.zeros((height * stride, 4))  # r, g, b, z sums of T * alpha * value
    accumulate(
        order,
        np.zeros(order.shape[0], dtype=np.int64),
        means2d,
        conics,
        opacities,
        colors,
        depths,
        half,
        width,
        height,
        T,
        acc,
        *_NO_LOG,
    )
    slots_to_pixels(acc, T, width, background, rgb.reshape(-1, 3), alpha.reshape(-1), depth.reshape(-1), True)


@njit(cache=True, nogil=True)
def slots_to_pixels(acc, T, width, background, rgb, trans, depth, as_alpha) -> None:
    """The compositor's per-slot sums as per-pixel outputs, leaving out each stacked row's end slot: acc [S, 4] (r, g,
    b, z sums) and T [S] with S = rows * (width + 1), background [3] -> rgb [rows * width, 3] (sums + T_final *
    background), trans [rows * width] (T_final, or 1 - T_final with `as_alpha`), depth [rows * width], in the
    outputs' dtype. Compiled because numpy over the slots' strided views took most of a 512² frame."""
    rows = T.shape[0] // (width + 1)
    b0, b1, b2 = background[0], background[1], background[2]
    for y in range(rows):
        for x in range(width):
            p, q = y * (width + 1) + x, y * width + x
            t = T[p]
            rgb[q, 0], rgb[q, 1], rgb[q, 2] = acc[p, 0] + t * b0, acc[p, 1] + t * b1, acc[p, 2] + t * b2
            trans[q] = 1.0 - t if as_alpha else t
            depth[q] = acc[p, 3]


@njit(cache=True, nogil=True)
def pixels_to_slots(g_rgb, g_trans, g_depth, T, width, g_acc, tail) -> None:
    """The per-pixel gradients back on the compositor's slots (the inverse of `slots_to_pixels`): g_acc [S, 4] =
    (dL/drgb, dL/ddepth) and tail [S] = T_final dL/dT_final, zero on each row's end slot. A gradient array of size 0
    stands for an output that got no gradient. (Compiled: numpy's zero fills and strided copies were a large share
    of a 512² step.)"""
    rows = T.shape[0] // (width + 1)
    for y in range(rows):
        for x in range(width + 1):
            p, q = y * (width + 1) + x, y * width + x
            inside = x < width
            for k in range(3):
                g_acc[p, k] = g_rgb[q, k] if inside and g_rgb.shape[0] else 0.0
            g_acc[p, 3] = g_depth[q] if inside and g_depth.shape[0] else 0.0
            tail[p] = T[p] * g_trans[q] if inside and g_trans.shape[0] else 0.0
