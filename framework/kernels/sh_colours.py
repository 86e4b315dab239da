"""`framework.splat.sh.view_colour_dc` and the rasterizer's SH colours as compiled loops over the Gaussians (numba) on
the CPU; the view colour also with a hand-written backward, for training steps.

Why: a frame renders one camera, so the avatar hands the rasterizer each Gaussian's colour towards it, evaluated at R^T
d in the Gaussian's skinning frame (`Avatar.forward`). In torch that is some 40 operations over [N] and [N, 16, 3]
tensors, a visible share of a CPU frame, in novel views as in novel poses. Per Gaussian the work is a 3x3 product, a
normalisation, 16 basis values and a [16] x [16, 3] product, which one pass does without per-operation overhead. The
numba rasterizer's own colours (SH of degree > 0 handed to it: static scenes, several cameras at once) are the same loop
without the frame.

A training step pays the torch path forward and backward, about twice the compiled loops' time. The backward carries the
colour's gradient to the active coefficients (the others get zero, as the torch path's slice), through the basis
polynomials' slopes and the direction's normalisation (none through the length below its floor, as `clamp_min`) to d and
to the frame R.

The same rules as `framework.splat.sh`: the direction normalised with its length floored at NORM_EPS (a zero
direction keeps only the constant term), the 3DGS/gsplat constants and signs, the first (degree + 1)^2 coefficients.
The arithmetic runs in float64 and the result is stored in the coefficients' dtype; it agrees with the torch path to
float32 rounding (`tests/test_compiled_sh.py` checks values and gradients against the torch path in float64).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit
from torch import Tensor

from framework.guards import NORM_EPS
from framework.splat.sh import SH_C0, SH_C1, SH_C2, SH_C3, num_sh_bases

_C2_0, _C2_1, _C2_2, _C2_3, _C2_4 = SH_C2
_C3_0, _C3_1, _C3_2, _C3_3, _C3_4, _C3_5, _C3_6 = SH_C3


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _fill_basis(degree, x, y, z, basis) -> None:
    """basis[:(degree + 1)^2] = the SH basis at the direction (x, y, z), normalised here (its length floored at
    NORM_EPS, as `framework.splat.sh.sh_basis`)."""
    norm = max(math.sqrt(x * x + y * y + z * z), NORM_EPS)
    x, y, z = x / norm, y / norm, z / norm
    basis[0] = SH_C0
    if degree >= 1:
        basis[1], basis[2], basis[3] = -SH_C1 * y, SH_C1 * z, -SH_C1 * x
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        basis[4], basis[5] = _C2_0 * xy, _C2_1 * yz
        basis[6] = _C2_2 * (2.0 * zz - xx - yy)
        basis[7], basis[8] = _C2_3 * xz, _C2_4 * (xx - yy)
        if degree >= 3:
            basis[9] = _C3_0 * y * (3.0 * xx - yy)
            basis[10] = _C3_1 * xy * z
            basis[11] = _C3_2 * y * (4.0 * zz - xx - yy)
            basis[12] = _C3_3 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
            basis[13] = _C3_4 * x * (4.0 * zz - xx - yy)
            basis[14] = _C3_5 * z * (xx - yy)
            basis[15] = _C3_6 * x * (xx - 3.0 * yy)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _dot(degree, basis, coeffs, n, c) -> float:
    """sum_b basis[b] coeffs[n, b, c] over the (degree + 1)^2 active coefficients."""
    acc = 0.0
    for b in range((degree + 1) * (degree + 1)):
        acc += basis[b] * coeffs[n, b, c]
    return acc


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _local_direction(dirs, frames, n):
    """R_n^T d_n, Gaussian n's direction from the camera in its skinning frame: (x, y, z)."""
    d0, d1, d2 = dirs[n, 0], dirs[n, 1], dirs[n, 2]
    x = d0 * frames[n, 0, 0] + d1 * frames[n, 1, 0] + d2 * frames[n, 2, 0]  # (d^T R)_j = (R^T d)_j
    y = d0 * frames[n, 0, 1] + d1 * frames[n, 1, 1] + d2 * frames[n, 2, 1]
    z = d0 * frames[n, 0, 2] + d1 * frames[n, 1, 2] + d2 * frames[n, 2, 2]
    return x, y, z


@njit(cache=True, nogil=True, error_model="numpy")
def view_colour_dc_rows(degree, coeffs, dirs, frames, start, stop, out) -> None:
    """out[n, 0, :] = SH(R_n^T d_n) / SH_C0 for coeffs [N, K, 3], dirs [N, 3] (unnormalised), frames [N, 3, 3], for
    Gaussians start..stop."""
    basis = np.empty(16)
    for n in range(start, stop):
        x, y, z = _local_direction(dirs, frames, n)
        _fill_basis(degree, x, y, z, basis)
        for c in range(3):
            out[n, 0, c] = _dot(degree, basis, coeffs, n, c) / SH_C0


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _basis_slope(degree, x, y, z, g):
    """sum_b g[b] d basis_b / d(x, y, z) at the unit direction (x, y, z), each basis function taken as the
    polynomial `_fill_basis` writes (as autograd differentiates `framework.splat.sh.sh_basis`)."""
    sx = sy = sz = 0.0
    if degree >= 1:
        sx, sy, sz = -SH_C1 * g[3], -SH_C1 * g[1], SH_C1 * g[2]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        sx += _C2_0 * y * g[4] - 2.0 * _C2_2 * x * g[6] + _C2_3 * z * g[7] + 2.0 * _C2_4 * x * g[8]
        sy += _C2_0 * x * g[4] + _C2_1 * z * g[5] - 2.0 * _C2_2 * y * g[6] - 2.0 * _C2_4 * y * g[8]
        sz += _C2_1 * y * g[5] + 4.0 * _C2_2 * z * g[6] + _C2_3 * x * g[7]
        if degree >= 3:
            sx += (
                6.0 * _C3_0 * xy * g[9]
                + _C3_1 * yz * g[10]
                - 2.0 * _C3_2 * xy * g[11]
                - 6.0 * _C3_3 * xz * g[12]
                + _C3_4 * (4.0 * zz - 3.0 * xx - yy) * g[13]
                + 2.0 * _C3_5 * xz * g[14]
                + 3.0 * _C3_6 * (xx - yy) * g[15]
            )
            sy += (
                3.0 * _C3_0 * (xx - yy) * g[9]
                + _C3_1 * xz * g[10]
                + _C3_2 * (4.0 * zz - xx - 3.0 * yy) * g[11]
                - 6.0 * _C3_3 * yz * g[12]
                - 2.0 * _C3_4 * xy * g[13]
                - 2.0 * _C3_5 * yz * g[14]
                - 6.0 * _C3_6 * xy * g[15]
            )
            sz += (
                _C3_1 * xy * g[10]
                + 8.0 * _C3_2 * yz * g[11]
                + 3.0 * _C3_3 * (2.0 * zz - xx - yy) * g[12]
                + 8.0 * _C3_4 * xz * g[13]
                + _C3_5 * (xx - yy) * g[14]
            )
    return sx, sy, sz


@njit(cache=True, nogil=True, error_model="numpy")
def view_colour_dc_backward(degree, coeffs, dirs, frames, grad, start, stop, g_coeffs, g_dirs, g_frames) -> None:
    """The gradients of `view_colour_dc_rows` for Gaussians start..stop: grad [N, 1, 3] -> g_coeffs [N, K, 3] (zero
    past the active bands), g_dirs [N, 3], g_frames [N, 3, 3]. The direction's normalisation as `sh_basis`: its
    length floored at NORM_EPS, and below the floor a plain division (no gradient through the length)."""
    basis, g_basis = np.empty(16), np.empty(16)
    k = (degree + 1) * (degree + 1)
    for n in range(start, stop):
        vx, vy, vz = _local_direction(dirs, frames, n)
        _fill_basis(degree, vx, vy, vz, basis)
        g0, g1, g2 = grad[n, 0, 0] / SH_C0, grad[n, 0, 1] / SH_C0, grad[n, 0, 2] / SH_C0
        for b in range(k):
            g_coeffs[n, b, 0], g_coeffs[n, b, 1], g_coeffs[n, b, 2] = basis[b] * g0, basis[b] * g1, basis[b] * g2
            g_basis[b] = coeffs[n, b, 0] * g0 + coeffs[n, b, 1] * g1 + coeffs[n, b, 2] * g2
        for b in range(k, coeffs.shape[1]):
            g_coeffs[n, b, 0] = g_coeffs[n, b, 1] = g_coeffs[n, b, 2] = 0.0
        length = math.sqrt(vx * vx + vy * vy + vz * vz)
        norm = max(length, NORM_EPS)
        x, y, z = vx / norm, vy / norm, vz / norm
        sx, sy, sz = _basis_slope(degree, x, y, z, g_basis)
        if length >= NORM_EPS:  # u = v / |v|: the slope's part along u drops out
            along = x * sx + y * sy + z * sz
            sx, sy, sz = sx - x * along, sy - y * along, sz - z * along
        sx, sy, sz = sx / norm, sy / norm, sz / norm  # the gradient at v = R^T d
        for i in range(3):
            g_dirs[n, i] = frames[n, i, 0] * sx + frames[n, i, 1] * sy + frames[n, i, 2] * sz
            d = dirs[n, i]
            g_frames[n, i, 0], g_frames[n, i, 1], g_frames[n, i, 2] = d * sx, d * sy, d * sz


@njit(cache=True, nogil=True, error_model="numpy")
def _colours(degree, coeffs, means, centres, out) -> None:
    """out[v, n, :] = max(SH(means[n] - centres[v]) + 0.5, 0): coeffs [N, K, 3], means [N, 3], centres [C, 3]."""
    basis = np.empty(16)
    for v in range(centres.shape[0]):
        for n in range(coeffs.shape[0]):
            _fill_basis(
                degree, means[n, 0] - centres[v, 0], means[n, 1] - centres[v, 1], means[n, 2] - centres[v, 2], basis
            )
            for c in range(3):
                out[v, n, c] = max(_dot(degree, basis, coeffs, n, c) + 0.5, 0.0)


def _check(degree: int, coeffs: Tensor) -> None:
    if not 0 <= degree <= 3 or coeffs.shape[-2] < num_sh_bases(degree):
        raise ValueError(
            f"sh colours: sh_degree {degree} needs 0..3 and at least {num_sh_bases(max(degree, 0))} coefficients "
            f"along dim -2, found shape {tuple(coeffs.shape)}; pass an sh_degree the coefficients hold."
        )


def sh_colours_compiled(degree: int, coeffs: Tensor, means: Tensor, centres: Tensor) -> np.ndarray:
    """`plugins.rasterizer.torch_ref.sh_colors` for every camera: colour = SH(mean - centre) + 0.5, clamped at 0,
    as a float64 array [C, N, 3] (what the compiled compositor reads); CPU tensors, no gradients."""
    _check(degree, coeffs)
    c, m, v = (t.detach().contiguous().numpy() for t in (coeffs, means.to(coeffs.dtype), centres.to(coeffs.dtype)))
    out = np.empty((v.shape[0], c.shape[0], 3))
    _colours(degree, c, m, v, out)
    return out


def _view_colour(
    degree: int, coeffs: Tensor, dirs: Tensor, frames: Tensor
) -> tuple[Tensor, tuple[Tensor, Tensor, Tensor]]:
    """The compiled forward on detached, contiguous copies in the coefficients' dtype -> [N, 1, 3] (and the inputs as
    the loops read them, for a backward)."""
    c, d, r = (t.detach().to(coeffs.dtype).contiguous() for t in (coeffs, dirs, frames))
    out = c.new_empty(c.shape[0], 1, 3)
    view_colour_dc_rows(degree, c.numpy(), d.numpy(), r.numpy(), 0, c.shape[0], out.numpy())
    return out, (c, d, r)


class _ViewColour(torch.autograd.Function):
    """(coeffs [N, K, 3], dirs [N, 3], frames [N, 3, 3]) -> [N, 1, 3], differentiable in all three (a training
    step's, on the CPU). One thread: split between two, the hand-off costs more than half of what the loop saves."""

    @staticmethod
    def forward(ctx, coeffs, dirs, frames, degree):  # type: ignore[override]
        out, read = _view_colour(degree, coeffs, dirs, frames)
        ctx.save_for_backward(*read)
        ctx.degree, ctx.dtypes = degree, (dirs.dtype, frames.dtype)
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):  # type: ignore[override]
        c, d, r = ctx.saved_tensors
        g = grad.to(c.dtype).contiguous()
        g_c, g_d, g_r = torch.empty_like(c), torch.empty_like(d), torch.empty_like(r)
        args = (ctx.degree, c.numpy(), d.numpy(), r.numpy(), g.numpy(), 0, c.shape[0])
        view_colour_dc_backward(*args, g_c.numpy(), g_d.numpy(), g_r.numpy())
        return g_c, g_d.to(ctx.dtypes[0]), g_r.to(ctx.dtypes[1]), None


def view_colour_dc_compiled(degree: int, coeffs: Tensor, dirs: Tensor, frames: Tensor) -> Tensor:
    """`framework.splat.sh.view_colour_dc` (the DC coefficients [N, 1, 3] that render as the colour towards the
    camera) through the compiled loops: CPU float tensors. With gradients (a training step) it is an autograd
    Function with a compiled backward."""
    _check(degree, coeffs)
    if torch.is_grad_enabled() and any(t.requires_grad for t in (coeffs, dirs, frames)):
        return _ViewColour.apply(coeffs, dirs, frames, degree)
    return _view_colour(degree, coeffs, dirs, frames)[0]
