"""The rasterizer contract's forward pass as compiled loops (numba): projection and front-to-back compositing.

Why: at the resolutions a CPU renders in real time (128-512 px) the eager `torch_ref` frame is mostly per-operation
overhead. Its projection alone is about 300 small tensor operations and its compositor about a thousand, each a few
microseconds, however few Gaussians there are (`tools/bench_render.py --scaling`: 4-6 ms of fixed cost per 128²
frame). A loop compiled once does the same arithmetic without that overhead. It also needs no pair list, no sort
and no per-pair buffers: the entries are visited in depth order, and each visit updates the transmittance and the
sums of the pixels its footprint covers. That is front-to-back compositing pixel by pixel, as the contract
(`framework.interfaces.rasterizer`) defines it, because a pixel sees its entries in the same order either way.

Forward only: `plugins/rasterizer/numba_cpu.py` hands every render that needs gradients to `torch_ref`, so there is one
implementation of the backward. Everything is computed in float64 and the results are cast to the caller's dtype.
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
def project(means, quats, scales, opacities, K, world_to_cam, width, height, near, far, eps2d,
            means2d, conics, depths, half, radii, valid):  # fmt: skip
    """EWA projection of N Gaussians into C cameras, the rules of `framework.splat.projection.project_gaussians`.

    In: means [N, 3], quats [N, 4] (wxyz, any norm), scales [N, 3], opacities [N], K [C, 3, 3], world_to_cam
    [C, 4, 4]. Out (written): means2d [C, N, 2], conics [C, N, 3], depths [C, N], half [C, N, 2] (0 where culled),
    radii [C, N] (0 where culled), valid [C, N]."""
    C, N = K.shape[0], means.shape[0]
    extend = np.empty(N)
    for n in range(N):
        extend[n] = min(math.sqrt(2.0 * math.log(max(opacities[n] / ALPHA_MIN, 1.0))), EXTEND_MAX)
    for c in range(C):
        fx, fy, cx, cy = K[c, 0, 0], K[c, 1, 1], K[c, 0, 2], K[c, 1, 2]
        u_lo, v_lo = -(cx + 0.5 * FOV_MARGIN * width) / fx, -(cy + 0.5 * FOV_MARGIN * height) / fy
        u_hi, v_hi = ((1.0 + 0.5 * FOV_MARGIN) * width - cx) / fx, ((1.0 + 0.5 * FOV_MARGIN) * height - cy) / fy
        Rc = world_to_cam[c, :3, :3]
        for n in range(N):
            x = Rc[0, 0] * means[n, 0] + Rc[0, 1] * means[n, 1] + Rc[0, 2] * means[n, 2] + world_to_cam[c, 0, 3]
            y = Rc[1, 0] * means[n, 0] + Rc[1, 1] * means[n, 1] + Rc[1, 2] * means[n, 2] + world_to_cam[c, 1, 3]
            z = Rc[2, 0] * means[n, 0] + Rc[2, 1] * means[n, 1] + Rc[2, 2] * means[n, 2] + world_to_cam[c, 2, 3]
            in_depth = z > near and z < far
            rz = 1.0 / z if in_depth else 1.0
            u, v = x * rz, y * rz
            mx, my = cx + fx * u, cy + fy * v
            # rotation of the normalised quaternion (a norm <= 1e-12 counts as the identity), times the scales
            w, qx, qy, qz = quats[n, 0], quats[n, 1], quats[n, 2], quats[n, 3]
            qn = math.sqrt(max(w * w + qx * qx + qy * qy + qz * qz, 1e-24))
            if qn > 1e-12:
                w, qx, qy, qz = w / qn, qx / qn, qy / qn, qz / qn
            else:
                w, qx, qy, qz = 1.0, 0.0, 0.0, 0.0
            rs = np.empty((3, 3))
            rs[0, 0], rs[0, 1], rs[0, 2] = 1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - w * qz), 2 * (qx * qz + w * qy)
            rs[1, 0], rs[1, 1], rs[1, 2] = 2 * (qx * qy + w * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - w * qx)
            rs[2, 0], rs[2, 1], rs[2, 2] = 2 * (qx * qz - w * qy), 2 * (qy * qz + w * qx), 1 - 2 * (qx * qx + qy * qy)
            uc, vc = min(max(u, u_lo), u_hi), min(max(v, v_lo), v_hi)
            t0 = np.empty(3)
            t1 = np.empty(3)
            for j in range(3):  # column j of W R S, then the Jacobian's two rows applied to it
                s = scales[n, j]
                w0 = (Rc[0, 0] * rs[0, j] + Rc[0, 1] * rs[1, j] + Rc[0, 2] * rs[2, j]) * s
                w1 = (Rc[1, 0] * rs[0, j] + Rc[1, 1] * rs[1, j] + Rc[1, 2] * rs[2, j]) * s
                w2 = (Rc[2, 0] * rs[0, j] + Rc[2, 1] * rs[1, j] + Rc[2, 2] * rs[2, j]) * s
                t0[j] = (w0 - uc * w2) * (fx * rz)
                t1[j] = (w1 - vc * w2) * (fy * rz)
            cxx = t0[0] * t0[0] + t0[1] * t0[1] + t0[2] * t0[2] + eps2d
            cxy = t0[0] * t1[0] + t0[1] * t1[1] + t0[2] * t1[2]
            cyy = t1[0] * t1[0] + t1[1] * t1[1] + t1[2] * t1[2] + eps2d
            cross_sq = ((t0[1] * t1[2] - t0[2] * t1[1]) ** 2 + (t0[2] * t1[0] - t0[0] * t1[2]) ** 2
                        + (t0[0] * t1[1] - t0[1] * t1[0]) ** 2)  # fmt: skip
            det = cross_sq + eps2d * (cxx + cyy - eps2d)  # Lagrange's identity, as the projection
            ok_det = det > 0
            inv = 1.0 / det if ok_det else 1.0
            means2d[c, n, 0], means2d[c, n, 1] = mx, my
            conics[c, n, 0], conics[c, n, 1], conics[c, n, 2] = cyy * inv, -cxy * inv, cxx * inv
            depths[c, n] = z
            hx = math.sqrt(max(cxx, 0.0)) * extend[n]
            hy = math.sqrt(max(cyy, 0.0)) * extend[n]
            hx = 0.0 if math.isnan(hx) else min(hx, _BIG)
            hy = 0.0 if math.isnan(hy) else min(hy, _BIG)
            rx, ry = math.ceil(hx), math.ceil(hy)
            inside = mx + rx > 0 and mx - rx < width and my + ry > 0 and my - ry < height
            finite = (math.isfinite(mx) and math.isfinite(my) and math.isfinite(cxx) and math.isfinite(cxy)
                      and math.isfinite(cyy))  # fmt: skip
            radius = max(rx, ry)
            ok = in_depth and ok_det and opacities[n] >= ALPHA_MIN and inside and finite and radius > 0
            valid[c, n] = ok
            radii[c, n] = int(radius) if ok else 0
            half[c, n, 0] = hx if ok else 0.0
            half[c, n, 1] = hy if ok else 0.0


@njit(cache=True, nogil=True)
def _next_open(skip, i: int) -> int:
    """The first pixel at or after slot `i` of its row that is not finished (path halving keeps the chains short)."""
    while skip[i] != i:
        skip[i] = skip[skip[i]]
        i = skip[i]
    return i


@njit(cache=True, nogil=True)
def composite(order, means2d, conics, opacities, colors, depths, half, width, height, background,
              rgb, alpha, depth):  # fmt: skip
    """Front-to-back compositing of one camera's entries `order` (indices, nearest first) into its image.

    In: means2d [N, 2], conics [N, 3], opacities [N], colors [N, 3], depths [N], half [N, 2], background [3].
    Out (written): rgb [H, W, 3], alpha [H, W], depth [H, W]. A pixel is finished when the transmittance after a pair
    would fall to 1e-4; that pair is not added (the contract's early termination).

    Finished pixels are skipped without being visited: each row keeps, per slot, a link towards the next pixel that
    is still open (a slot W past the row's end is never finished), so a span costs its open pixels, not its width.
    Where the footprints pile up (opaque surfaces, large Gaussians) most pairs fall on finished pixels: 30k random
    Gaussians of about 20 px radius at 256² measured 119 ms when every pair was visited, 51 ms this way.

    One thread: two threads on interleaved rows measured no faster on a 2-core VM (walking avatar frames at 128-512²,
    the two alternated: 4.6 against 4.6 ms at 128², 8.2 against 9.5 ms at 512²)."""
    stride = width + 1
    T = np.ones(height * stride)
    acc = np.zeros((height * stride, 4))  # r, g, b, z sums of T * alpha * value
    skip = np.arange(height * stride)  # skip[i] == i: open (or the row's end slot); else a link further right
    for e in order:
        mx, my = means2d[e, 0], means2d[e, 1]
        a, b, c = conics[e, 0], conics[e, 1], conics[e, 2]
        op = opacities[e]
        big_l = math.log(max(op / ALPHA_MIN, 1.0))  # sigma <= L wherever alpha can reach 1/255
        a_safe = max(a, _TINY)
        y0 = _clamp_index(math.ceil(my - half[e, 1] - BOX_MARGIN - 0.5), 0, height)
        y1 = _clamp_index(math.floor(my + half[e, 1] + BOX_MARGIN - 0.5), -1, height - 1)
        for y in range(y0, y1 + 1):
            dy = my - (y + 0.5)
            disc = (b * dy) ** 2 - a * (c * dy * dy - 2.0 * big_l)  # sigma(dx) <= L is a quadratic in dx
            if not disc >= 0:
                continue
            sq = math.sqrt(disc)
            x0 = _clamp_index(math.ceil(mx - (-b * dy + sq) / a_safe - BOX_MARGIN - 0.5), 0, width)
            x1 = _clamp_index(math.floor(mx - (-b * dy - sq) / a_safe + BOX_MARGIN - 0.5), -1, width - 1)
            row = y * stride
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
                p = _next_open(skip, p + 1)
    for i in range(height):
        for j in range(width):
            p = i * stride + j
            for k in range(3):
                rgb[i, j, k] = acc[p, k] + T[p] * background[k]
            alpha[i, j] = 1.0 - T[p]
            depth[i, j] = acc[p, 3]
