"""`framework.splat.sh.view_colour_dc` and the rasterizer's SH colours as compiled loops over the Gaussians (numba),
for renders without gradients on the CPU.

Why: a frame renders one camera, so the avatar hands the rasterizer each Gaussian's colour towards it, evaluated at
R^T d in the Gaussian's skinning frame (`Avatar.forward`). In torch that is some 40 operations over [N] and
[N, 16, 3] tensors: about 1 ms of a 512² CPU frame of the trained default avatar (6375 Gaussians, degree 3), in its
novel views as in its novel poses. Per Gaussian the work is a 3x3 product, a normalisation, 16 basis values and a
[16] x [16, 3] product, which one pass does without per-operation overhead. The numba rasterizer's own colours (SH
of degree > 0 handed to it: static scenes, several cameras at once) are the same loop without the frame.

The same rules as `framework.splat.sh`: the direction normalised with its length floored at NORM_EPS (a zero
direction keeps only the constant term), the 3DGS/gsplat constants and signs, the first (degree + 1)^2 coefficients.
The arithmetic runs in float64 and the result is stored in the coefficients' dtype; it agrees with the torch path to
float32 rounding (`tests/test_compiled_sh.py` checks it against the torch path in float64).
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


@njit(cache=True, nogil=True, error_model="numpy")
def _view_colour_dc(degree, coeffs, dirs, frames, out) -> None:
    """out[n, 0, :] = SH(R_n^T d_n) / SH_C0 for coeffs [N, K, 3], dirs [N, 3] (unnormalised), frames [N, 3, 3]."""
    basis = np.empty(16)
    for n in range(coeffs.shape[0]):
        d0, d1, d2 = dirs[n, 0], dirs[n, 1], dirs[n, 2]
        x = d0 * frames[n, 0, 0] + d1 * frames[n, 1, 0] + d2 * frames[n, 2, 0]  # (d^T R)_j = (R^T d)_j
        y = d0 * frames[n, 0, 1] + d1 * frames[n, 1, 1] + d2 * frames[n, 2, 1]
        z = d0 * frames[n, 0, 2] + d1 * frames[n, 1, 2] + d2 * frames[n, 2, 2]
        _fill_basis(degree, x, y, z, basis)
        for c in range(3):
            out[n, 0, c] = _dot(degree, basis, coeffs, n, c) / SH_C0


@njit(cache=True, nogil=True, error_model="numpy")
def _colours(degree, coeffs, means, centres, out) -> None:
    """out[v, n, :] = max(SH(means[n] - centres[v]) + 0.5, 0): coeffs [N, K, 3], means [N, 3], centres [C, 3]."""
    basis = np.empty(16)
    for v in range(centres.shape[0]):
        for n in range(coeffs.shape[0]):
            _fill_basis(degree, means[n, 0] - centres[v, 0], means[n, 1] - centres[v, 1], means[n, 2] - centres[v, 2],
                        basis)  # fmt: skip
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


def view_colour_dc_compiled(degree: int, coeffs: Tensor, dirs: Tensor, frames: Tensor) -> Tensor:
    """`framework.splat.sh.view_colour_dc` (the DC coefficients [N, 1, 3] that render as the colour towards the
    camera) through the compiled loop: CPU tensors of one float dtype, no gradients."""
    _check(degree, coeffs)
    c, d, r = (t.detach().contiguous().numpy() for t in (coeffs, dirs.to(coeffs.dtype), frames.to(coeffs.dtype)))
    out = np.empty((c.shape[0], 1, 3), dtype=c.dtype)
    _view_colour_dc(degree, c, d, r, out)
    return torch.from_numpy(out)
