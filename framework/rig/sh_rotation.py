"""Rotate real SH coefficients (degrees 1-3, the 3DGS/gsplat basis of `framework.splat.sh`) by rotation matrices.

Rotating a Gaussian by R must rotate its view-dependent colour: the new coefficients c' satisfy
f'(d) = f(R^T d) for every direction d. Each degree l is closed under rotation, Y_l(R^T d) = D_l(R) Y_l(d), so c'_l is
determined exactly by the values of f' at any 2l + 1 directions where Y_l is well conditioned:

    c'_l = P_l @ (Y_l(R^T d_1..d_M) @ c_l),   P_l = pinv(Y_l(d_1..d_M)) (constant, float64 once)

with M = 7 fixed directions (chosen by a seeded search so that every Y_l block has condition number <= 3.3), i.e.
one basis evaluation at 7 rotated directions per Gaussian and two small contractions per degree. Why this instead of
the Ivanic-Ruedenberg recurrences: it reuses the renderer's own basis (so signs and constants cannot drift from it),
is a handful of lines, exact up to rounding, differentiable in R with plain autograd, and vectorises over N.

Degree 1 takes its closed form instead: Y_1(d) = C1 (-y, z, -x) is a signed permutation of d, so the block's rotation
matrix is R with rows and columns permuted and signed (no basis evaluation; measured 3x cheaper forward+backward).
Only the degrees present are rotated: a model whose SH schedule has not reached degree 3 passes fewer coefficients.
"""

from __future__ import annotations

import torch
from torch import Tensor

from framework.execution import COMPILED, Execution
from framework.splat.sh import sh_basis

# Seeded search (numpy/torch Generator 0, best of 3000 random 7-point sets) for the smallest max condition number
# of the degree-1..3 blocks of the basis: 3.21.
_DIRS = (
    (-0.5390104237289924, 0.5311745862623111, 0.6536981887848206),
    (-0.8117586191312032, -0.03344956936500528, 0.583034364832381),
    (0.21090061250325065, 0.23651967997706524, 0.9484615820523783),
    (-0.791185047420091, -0.6106067792083263, -0.034432280257089574),
    (-0.8206513659043536, -0.4116894045862199, -0.3962867267405792),
    (0.9600656733374803, -0.2774580132077107, -0.03592984533615946),
    (0.24364255355637027, -0.9372676993820127, 0.24933424512425142),
)
_cache: dict[tuple[torch.dtype, torch.device], tuple[Tensor, list[Tensor]]] = {}
# Degree 1: Y_1(d) = C1 * M d with M = rows (-e_y, e_z, -e_x), so the block rotates by M R M^T = (s s^T) o R[p][:, p].
_DEG1_PERM = (1, 2, 0)
_DEG1_SIGN = ((1.0, -1.0, 1.0), (-1.0, 1.0, -1.0), (1.0, -1.0, 1.0))
_deg1_cache: dict[tuple[torch.dtype, torch.device], tuple[Tensor, Tensor]] = {}


def _degree1_rotation(R: Tensor) -> Tensor:
    """R [N, 3, 3] -> the degree-1 block's rotation [N, 3, 3] (row k gives rotated coefficient k)."""
    key = (R.dtype, R.device)
    if key not in _deg1_cache:
        _deg1_cache[key] = (
            torch.tensor(_DEG1_PERM, device=R.device),
            torch.tensor(_DEG1_SIGN, dtype=R.dtype, device=R.device),
        )
    perm, sign = _deg1_cache[key]
    return R.index_select(-2, perm).index_select(-1, perm) * sign


def _sample_dirs_and_pinvs(dtype: torch.dtype, device: torch.device) -> tuple[Tensor, list[Tensor]]:
    key = (dtype, device)
    if key not in _cache:
        D = torch.tensor(_DIRS, dtype=torch.float64)
        D = D / D.norm(dim=-1, keepdim=True)  # [M, 3]
        Y = sh_basis(3, D)  # [M, 16]
        pinvs = [torch.linalg.pinv(Y[:, l * l : (l + 1) ** 2]).to(dtype=dtype, device=device) for l in (1, 2, 3)]
        _cache[key] = (D.to(dtype=dtype, device=device), pinvs)  # D [M, 3], P_l [2l+1, M]
    return _cache[key]


def rotate_sh(sh: Tensor, R: Tensor, execution: Execution = COMPILED) -> Tensor:
    """sh [N, K, C] (K = (d+1)^2, d <= 3), R [N, 3, 3] (or [3, 3] shared) -> rotated sh [N, K, C].

    The DC term is unchanged; degrees 1..d are rotated so that eval(rotated, d) = eval(sh, R^T d).
    """
    K = sh.shape[-2]
    degree = int(round(K**0.5)) - 1
    if (degree + 1) ** 2 != K or degree > 3:
        raise ValueError(f"rotate_sh: expected K = (d+1)^2 coefficients with d <= 3 along dim -2, got K = {K}.")
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"rotate_sh: expected rotations [N, 3, 3], got shape {tuple(R.shape)}.")
    if degree == 0 or sh.shape[0] == 0:
        return sh
    compute = torch.promote_types(sh.dtype, torch.float32)  # half-precision inputs are rotated in float32
    N = sh.shape[0]
    Rc = R.to(compute).expand(N, 3, 3)  # [N, 3, 3] (a shared rotation is broadcast)
    shc = sh.to(compute)
    out = [shc[:, :1], _degree1_rotation(Rc) @ shc[:, 1:4]]  # [N, 1, C], [N, 3, C]
    if degree >= 2:
        D, pinvs = _sample_dirs_and_pinvs(compute, sh.device)
        Y = sh_basis(degree, torch.matmul(D, Rc), execution=execution)  # [N, M, K] at R^T d_m (row m of D R)
        M = D.shape[0]
        for l in range(2, degree + 1):
            lo, hi = l * l, (l + 1) ** 2
            values = Y[..., lo:hi] @ shc[:, lo:hi]  # [N, M, C] = f_l(R^T d_m)
            rotated = pinvs[l - 1] @ values.transpose(0, 1).reshape(M, -1)  # [2l+1, N * C]
            out.append(rotated.reshape(hi - lo, N, -1).transpose(0, 1))  # [N, 2l+1, C]
    return torch.cat(out, dim=1).to(sh.dtype)
