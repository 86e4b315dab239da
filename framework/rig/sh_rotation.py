"""Rotate real SH coefficients (degrees 1-3, the 3DGS/gsplat basis of `framework.splat.sh`) by rotation matrices.

Rotating a Gaussian by R must rotate its view-dependent colour: the new coefficients c' satisfy
f'(d) = f(R^T d) for every direction d. Each degree l is closed under rotation, Y_l(R^T d) = D_l(R) Y_l(d), so c'_l is
determined exactly by the values of f' at any 2l + 1 directions where Y_l is well conditioned:

    c'_l = P_l @ (Y_l(R^T d_1..d_M) @ c_l),   P_l = pinv(Y_l(d_1..d_M)) (constant, float64 once)

with M = 7 fixed directions (chosen by a seeded search so that every Y_l block has condition number <= 3.3), i.e.
one basis evaluation at 7 rotated directions per Gaussian and two small contractions per degree. Why this instead of
the Ivanic-Ruedenberg recurrences: it reuses the renderer's own basis (so signs and constants cannot drift from it),
is a handful of lines, exact up to rounding, differentiable in R with plain autograd, and vectorises over N.
"""

from __future__ import annotations

import torch
from torch import Tensor

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


def _sample_dirs_and_pinvs(dtype: torch.dtype, device: torch.device) -> tuple[Tensor, list[Tensor]]:
    key = (dtype, device)
    if key not in _cache:
        D = torch.tensor(_DIRS, dtype=torch.float64)
        D = D / D.norm(dim=-1, keepdim=True)  # [M, 3]
        Y = sh_basis(3, D)  # [M, 16]
        pinvs = [torch.linalg.pinv(Y[:, l * l : (l + 1) ** 2]).to(dtype=dtype, device=device) for l in (1, 2, 3)]
        _cache[key] = (D.to(dtype=dtype, device=device), pinvs)  # D [M, 3], P_l [2l+1, M]
    return _cache[key]


def rotate_sh(sh: Tensor, R: Tensor) -> Tensor:
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
    D, pinvs = _sample_dirs_and_pinvs(compute, sh.device)
    Rc = R.to(compute)
    dirs = torch.einsum("...ba,mb->...ma", Rc, D)  # [N, M, 3] = R^T d_m
    if dirs.dim() == 2:
        dirs = dirs.expand(sh.shape[0], -1, -1)
    Y = sh_basis(degree, dirs)  # [N, M, K]
    shc = sh.to(compute)
    out = [shc[:, :1]]
    for l in range(1, degree + 1):
        lo, hi = l * l, (l + 1) ** 2
        values = torch.einsum("nmk,nkc->nmc", Y[..., lo:hi], shc[:, lo:hi])  # [N, M, C] = f_l(R^T d_m)
        out.append(torch.einsum("km,nmc->nkc", pinvs[l - 1], values))  # [N, 2l+1, C]
    return torch.cat(out, dim=1).to(sh.dtype)
