"""The blend weights at the centres and the L_w term, as compiled loops with a hand-written backward (numba).

Why: in a training step the deformer looks up the weight grid at seven points per Gaussian (the centre and the six
L_w points x +- s_l a_l), combines the grid weights with F_dw's residual and takes the standard deviation over the six
points. In torch that is some forty operations over [N, 7, J] tensors each way, more than the compiled rasterizer
takes. Per
point the work is eight grid rows, a weighted sum over J and a few sums, which one pass does on both cores.

The same rules as the torch path, in float64 (the grid rows are float32 data):
- the lookup of `framework.rig.weight_field.WeightField.sample` on a partition-of-unity grid: node units
  u = (x - lo) / (hi - lo) * (R - 1), clamped to the box with zero gradient on and beyond its faces (NaN goes to
  node `WEIGHT_FIELD_NAN_NODE`), trilinear in the cell of the lower corner min(floor(u), R - 2);
- F_dw's combination (`plugins/deformer/lbs_residual.py`): "softmax" w = softmax(log(w0 + eps) + dw), computed as
  (w0 + eps) softmax(dw) / sum (torch's vectorised softmax of dw is the one exponential; the loops take no log or
  exp), "additive" w = w0 + dw, or the grid weights alone while F_dw is off;
- L_w of `framework.rig.lbs.weight_std`: per joint the standard deviation over the six points (population form),
  zero where the variance is at most `WEIGHT_VAR_MIN` (its slope is infinite at zero), summed over the joints.
The forward keeps the grid and the combined weights ([N, 7, J] each, in the points' dtype); the backward applies the
chain rule in reverse from them: d std / d w_k = (w_k - mean) / (6 std), the softmax's w (g - <w, g>), 1 / (w0 + eps)
through the log, and per point eight dot products of that gradient with the cell's corner rows, weighted by the
trilinear slopes. Each pass splits the Gaussians between threads (the loops release the GIL). Bodies with frozen
joints (a second field over the whole skeleton for L_w) keep the torch path. `tests/test_compiled_weights.py` checks
values and gradients against the torch path in float64 and by finite differences.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit
from torch import Tensor

from framework.guards import WEIGHT_FIELD_NAN_NODE, WEIGHT_VAR_MIN
from framework.kernels.threads import run_chunked
from framework.rig.weight_field import WeightField

#: F_dw's combination with the grid weights: none (F_dw off), softmax, additive (`LBSResidualDeformer.residual`)
COMBINE_MODES = {"none": 0, "softmax": 1, "additive": 2}

#: reassociation lets LLVM vectorise the sums over the joints; no flag that assumes finite values (the NaN test)
_FASTMATH = {"reassoc", "contract"}


@njit(cache=True, nogil=True, fastmath=_FASTMATH, inline="always")
def _cell(p, lo, hi, counts, corner, rows) -> None:
    """The trilinear stencil of the point p [3]: rows [8] of the cell's corners in the table, corner [4, 8] their
    weights and, in rows 1-3, the weights' slopes along x, y, z in the point's units (zero along an axis where the
    point is clamped to the box)."""
    base = 0
    stride = 1
    fx = fy = fz = 0.0
    sx = sy = sz = 0.0
    for a in range(3):
        m = counts[a] - 1
        scale = m / (hi[a] - lo[a])
        u = (p[a] - lo[a]) * scale
        if not (u > 0.0 and u < m):  # clamped: zero gradient, as grid_sample's border mode
            scale = 0.0
            if u != u:
                u = WEIGHT_FIELD_NAN_NODE
            u = min(max(u, 0.0), float(m))
        i0 = min(math.floor(u), m - 1)
        if a == 0:
            fx, sx = u - i0, scale
        elif a == 1:
            fy, sy = u - i0, scale
        else:
            fz, sz = u - i0, scale
        base += int(i0) * stride
        stride *= counts[a]
    W, H = counts[0], counts[1]
    c = 0
    for dz in range(2):
        wz, dz_ = (fz, sz) if dz else (1.0 - fz, -sz)
        for dy in range(2):
            wy, dy_ = (fy, sy) if dy else (1.0 - fy, -sy)
            for dx in range(2):
                wx, dx_ = (fx, sx) if dx else (1.0 - fx, -sx)
                rows[c] = base + (dz * H + dy) * W + dx
                corner[0, c] = wx * wy * wz
                corner[1, c] = dx_ * wy * wz
                corner[2, c] = wx * dy_ * wz
                corner[3, c] = wx * wy * dz_
                c += 1


@njit(cache=True, nogil=True, fastmath=_FASTMATH, inline="always")
def _gather(table, corner, rows, g) -> None:
    """Grid weights g [J] = the corners' rows weighted by corner[0] (corner-major, the joints innermost, so the
    loads and sums over J vectorise)."""
    J = table.shape[1]
    for j in range(J):
        g[j] = 0.0
    for c in range(8):
        row, weight = table[rows[c]], corner[0, c]
        for j in range(J):
            g[j] += weight * row[j]


@njit(cache=True, nogil=True, fastmath=_FASTMATH, inline="always")
def _combine(g, dw, n, k, mode, eps, w) -> None:
    """The weights w [J] from the grid's g [J] and dw[n, k] (see COMBINE_MODES): F_dw's residual (additive), or its
    softmax (softmax(log(g + eps) + dw) = (g + eps) exp(dw) / sum, and exp(dw) may be scaled per row, so no logarithm
    and no exponential is taken here)."""
    J = g.shape[0]
    if mode == 0:
        for j in range(J):
            w[j] = g[j]
    elif mode == 2:
        for j in range(J):
            w[j] = g[j] + dw[n, k, j]
    else:
        total = 0.0
        for j in range(J):
            w[j] = (g[j] + eps) * dw[n, k, j]
            total += w[j]
        for j in range(J):
            w[j] /= total


@njit(cache=True, nogil=True, fastmath=_FASTMATH, inline="always")
def _std_over_six(w, mean, std) -> float:
    """w [7, J] (row 0 the centre): per joint mean [J] and std [J] over rows 1-6 (zero at variance <= WEIGHT_VAR_MIN);
    returns their sum, L_w."""
    total = 0.0
    for j in range(w.shape[1]):
        m = 0.0
        for k in range(1, 7):
            m += w[k, j]
        m /= 6.0
        var = 0.0
        for k in range(1, 7):
            var += (w[k, j] - m) ** 2
        var /= 6.0
        mean[j] = m
        std[j] = math.sqrt(var) if var > WEIGHT_VAR_MIN else 0.0
        total += std[j]
    return total


@njit(cache=True, nogil=True, fastmath=_FASTMATH)
def smooth_weights_forward(
    points, table, lo, hi, counts, dw, mode, eps, start, stop, w_centre, l_w, grid_all, weights_all
) -> None:
    """points [N, 7, 3] (centre, then the six L_w points) -> w_centre [N, J], l_w [N], and for the backward the grid
    weights grid_all [N, 7, J] and the combined weights weights_all [N, 7, J], for Gaussians start..stop."""
    J = table.shape[1]
    g, w = np.empty(J), np.empty((7, J))
    mean, std = np.empty(J), np.empty(J)
    corner, rows = np.empty((4, 8)), np.empty(8, np.int64)
    for n in range(start, stop):
        for k in range(7):
            _cell(points[n, k], lo, hi, counts, corner, rows)
            _gather(table, corner, rows, g)
            _combine(g, dw, n, k, mode, eps, w[k])
            for j in range(J):
                grid_all[n, k, j] = g[j]
                weights_all[n, k, j] = w[k, j]
        for j in range(J):
            w_centre[n, j] = w[0, j]
        l_w[n] = _std_over_six(w, mean, std)


@njit(cache=True, nogil=True, fastmath=_FASTMATH)
def smooth_weights_backward(
    points,
    table,
    lo,
    hi,
    counts,
    mode,
    eps,
    grid_all,
    weights_all,
    grad_centre,
    grad_lw,
    start,
    stop,
    grad_points,
    grad_dw,
) -> None:
    """The forward's gradients, from its grid_all and weights_all [N, 7, J]: grad_centre [N, J], grad_lw [N] ->
    grad_points [N, 7, 3], grad_dw [N, 7, J] (mode 1 and 2), for Gaussians start..stop."""
    J = table.shape[1]
    gw, mean, std = np.empty(J), np.empty(J), np.empty(J)
    corner, rows = np.empty((4, 8)), np.empty(8, np.int64)
    for n in range(start, stop):
        w, g = weights_all[n], grid_all[n]  # [7, J]
        _std_over_six(w, mean, std)
        for k in range(7):
            if k == 0:
                for j in range(J):
                    gw[j] = grad_centre[n, j]
            else:
                for j in range(J):
                    gw[j] = grad_lw[n] * (w[k, j] - mean[j]) / (6.0 * std[j]) if std[j] > 0.0 else 0.0
            if mode == 1:  # softmax: dz = w (gw - <w, gw>), then d log(g + eps) = dz / (g + eps)
                inner = 0.0
                for j in range(J):
                    inner += w[k, j] * gw[j]
                for j in range(J):
                    dz = w[k, j] * (gw[j] - inner)
                    grad_dw[n, k, j] = dz
                    gw[j] = dz / (g[k, j] + eps)
            elif mode == 2:
                for j in range(J):
                    grad_dw[n, k, j] = gw[j]
            # d/dp_a = sum_c slope_a,c <row_c, gw>: one dot product per corner
            _cell(points[n, k], lo, hi, counts, corner, rows)
            sx = sy = sz = 0.0
            for c in range(8):
                row = table[rows[c]]
                dot = 0.0
                for j in range(J):
                    dot += gw[j] * row[j]
                sx += corner[1, c] * dot
                sy += corner[2, c] * dot
                sz += corner[3, c] * dot
            grad_points[n, k, 0], grad_points[n, k, 1], grad_points[n, k, 2] = sx, sy, sz


class _SmoothWeights(torch.autograd.Function):
    """points [N, 7, 3], dw [N, 7, J] or None -> (w_centre [N, J], l_w [N]); differentiable in points and dw."""

    @staticmethod
    def forward(ctx, points, dw, table, lo, hi, counts, mode, eps):  # type: ignore[override]
        n, J = points.shape[0], table.shape[1]
        p = points.detach().contiguous()
        if dw is None:
            d = points.new_zeros(0, 7, J)
        elif mode == COMBINE_MODES["softmax"]:  # the kernels take exp(dw) up to a factor per row: softmax(dw)
            d = torch.softmax(dw.detach().to(points.dtype), dim=-1).contiguous()  # [N, 7, J]
        else:
            d = dw.detach().to(points.dtype).contiguous()
        w_centre, l_w = points.new_empty(n, J), points.new_empty(n)
        grid_all, weights_all = points.new_empty(n, 7, J), points.new_empty(n, 7, J)
        fixed = (p.numpy(), table.numpy(), lo, hi, counts, d.numpy(), mode, eps)
        outputs = (w_centre.numpy(), l_w.numpy(), grid_all.numpy(), weights_all.numpy())
        run_chunked(smooth_weights_forward, fixed, outputs, n)
        ctx.save_for_backward(p, grid_all, weights_all)
        ctx.fixed = (table, lo, hi, counts, mode, eps)
        ctx.dw_dtype = dw.dtype if dw is not None else None
        return w_centre, l_w

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_centre, grad_lw):  # type: ignore[override]
        p, grid_all, weights_all = ctx.saved_tensors
        table, lo, hi, counts, mode, eps = ctx.fixed
        n, J = p.shape[0], table.shape[1]
        grad_centre = p.new_zeros(n, J) if grad_centre is None else grad_centre.to(p.dtype).contiguous()
        grad_lw = p.new_zeros(n) if grad_lw is None else grad_lw.to(p.dtype).contiguous()
        grad_points = p.new_empty(n, 7, 3)
        grad_dw = p.new_empty(n, 7, J) if mode else p.new_zeros(0, 7, J)
        fixed = (p.numpy(), table.numpy(), lo, hi, counts, mode, eps, grid_all.numpy(), weights_all.numpy())
        fixed += (grad_centre.numpy(), grad_lw.numpy())
        run_chunked(smooth_weights_backward, fixed, (grad_points.numpy(), grad_dw.numpy()), n)
        grad_dw_out = grad_dw.to(ctx.dw_dtype) if ctx.dw_dtype is not None else None
        return grad_points, grad_dw_out, None, None, None, None, None, None


def smooth_weights_compiled(
    field: WeightField, points: Tensor, dw: Tensor | None, combine: str, eps: float
) -> tuple[Tensor, Tensor]:
    """`LBSDeformerBase.smooth_weights` for a partition-of-unity `field` on the CPU: points [N, 7, 3] (the centre,
    then the six L_w points), F_dw's dw [N, 7, J] (None while it is off) combined as `combine` -> (weights [N, J] at
    the centres, L_w [N]), in the points' dtype."""
    if combine not in COMBINE_MODES or (dw is None) != (combine == "none"):
        raise ValueError(f"smooth_weights_compiled: combine '{combine}' with dw {'absent' if dw is None else 'given'}.")
    if not field.partition_of_unity:
        raise ValueError("smooth_weights_compiled: the grid's rows must sum to one (torch's path normalises them).")
    D, H, W = field.resolution
    counts = np.array([W, H, D], dtype=np.int64)  # nodes along x, y, z
    bounds = field.bounds.double().numpy()
    return _SmoothWeights.apply(points, dw, field.table, bounds[0], bounds[1], counts, COMBINE_MODES[combine], eps)
