"""Real spherical harmonics up to degree 3 with the 3DGS/gsplat constants and sign convention.

Every rasterizer backend turns SH coefficients into colours the same way, so the basis lives here once: colour =
eval_sh(...) + 0.5, clamped at 0 (the clamp is the backend's job). Directions are normalised here, so callers pass the
raw `mean - camera_centre` vector.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from framework.device_constants import constant_on
from framework.execution import COMPILED, Execution
from framework.geometry import few_kernels
from framework.guards import NORM_EPS

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)
MAX_SH_DEGREE = 3


def num_sh_bases(degree: int) -> int:
    """(degree + 1) ** 2 coefficients per colour channel."""
    return (degree + 1) ** 2


def sh_degree_of_bases(num_bases: int) -> int:
    """The degree whose (degree + 1) ** 2 coefficients `num_bases` holds (the inverse of `num_sh_bases`)."""
    return math.isqrt(num_bases) - 1


def _check_degree(degree: int) -> None:
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"sh_degree: expected an integer in 0..{MAX_SH_DEGREE}, got {degree}; lower the SH degree.")


def sh_basis(degree: int, dirs: Tensor, eps: float = NORM_EPS, execution: Execution = COMPILED) -> Tensor:
    """Basis functions [..., (degree+1)^2] at the normalised directions `dirs` [..., 3].

    A zero direction (camera exactly at the mean) gives the basis at (0, 0, 0): only the constant term survives,
    with finite gradients, rather than NaN.
    """
    _check_degree(degree)
    norm = dirs.norm(dim=-1, keepdim=True).clamp_min(eps)
    d = dirs / norm
    if degree >= 2 and few_kernels(d, execution):  # below degree 2 the entries are fewer operators than the gathers
        return _basis_from_monomials(degree, d)
    x, y, z = d.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        out += [
            SH_C2[0] * xy,
            SH_C2[1] * yz,
            SH_C2[2] * (2.0 * zz - xx - yy),
            SH_C2[3] * xz,
            SH_C2[4] * (xx - yy),
        ]
        if degree >= 3:
            out += [
                SH_C3[0] * y * (3.0 * xx - yy),
                SH_C3[1] * xy * z,
                SH_C3[2] * y * (4.0 * zz - xx - yy),
                SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
                SH_C3[4] * x * (4.0 * zz - xx - yy),
                SH_C3[5] * z * (xx - yy),
                SH_C3[6] * x * (xx - 3.0 * yy),
            ]
    return torch.stack(out, dim=-1)


def _monomial_tables() -> tuple[list[tuple[int, int, int]], Tensor, Tensor, Tensor, Tensor]:
    """The monomials x^a y^b z^c of degree <= 3 in the order `_basis_from_monomials` builds them (1; x, y, z; six of
    degree 2 from the [9] outer product d d^T; ten of degree 3 from the [18] products of those six with d), the two
    gathers that pick them, and each basis function as three (monomial, coefficient) terms, zero-padded: [48] indices
    and [48] float64 coefficients, basis k in entries 3k..3k+2."""
    mono = [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)]
    unit = mono[1:]
    pairs = [(i, j) for i in range(3) for j in range(3)]  # entry 3i + j of the outer product
    square_pick = [3 * i + j for i, j in pairs if i <= j]  # [6]
    squares = [tuple(a + b for a, b in zip(unit[i], unit[j], strict=True)) for i, j in pairs if i <= j]
    cube_pick, cubes = [], []
    for p, sq in enumerate(squares):
        for j in range(3):
            m = tuple(a + b for a, b in zip(sq, unit[j], strict=True))
            if m not in cubes:
                cube_pick.append(3 * p + j)
                cubes.append(m)
    mono += squares + cubes  # 20
    x, y, z = (1, 0, 0), (0, 1, 0), (0, 0, 1)

    def m(*factors: tuple[int, int, int]) -> tuple[int, int, int]:
        return tuple(sum(f[i] for f in factors) for i in range(3)) if factors else (0, 0, 0)

    polynomials = [  # each basis function as {monomial: coefficient}, written out from `sh_basis`'s formulas
        {m(): SH_C0},
        {m(y): -SH_C1},
        {m(z): SH_C1},
        {m(x): -SH_C1},
        {m(x, y): SH_C2[0]},
        {m(y, z): SH_C2[1]},
        {m(z, z): 2 * SH_C2[2], m(x, x): -SH_C2[2], m(y, y): -SH_C2[2]},
        {m(x, z): SH_C2[3]},
        {m(x, x): SH_C2[4], m(y, y): -SH_C2[4]},
        {m(x, x, y): 3 * SH_C3[0], m(y, y, y): -SH_C3[0]},
        {m(x, y, z): SH_C3[1]},
        {m(y, z, z): 4 * SH_C3[2], m(x, x, y): -SH_C3[2], m(y, y, y): -SH_C3[2]},
        {m(z, z, z): 2 * SH_C3[3], m(x, x, z): -3 * SH_C3[3], m(y, y, z): -3 * SH_C3[3]},
        {m(x, z, z): 4 * SH_C3[4], m(x, x, x): -SH_C3[4], m(x, y, y): -SH_C3[4]},
        {m(x, x, z): SH_C3[5], m(y, y, z): -SH_C3[5]},
        {m(x, x, x): SH_C3[6], m(x, y, y): -3 * SH_C3[6]},
    ]
    index, coef = [], []
    for poly in polynomials:
        terms = list(poly.items()) + [((0, 0, 0), 0.0)] * (3 - len(poly))
        index += [mono.index(t) for t, _ in terms]
        coef += [c for _, c in terms]
    as_long = lambda v: torch.tensor(v, dtype=torch.long)  # noqa: E731
    return mono, as_long(square_pick), as_long(cube_pick), as_long(index), torch.tensor(coef, dtype=torch.float64)


_MONOMIALS, _SQUARE_PICK, _CUBE_PICK, _TERM_INDEX, _TERM_COEF = _monomial_tables()


def _basis_from_monomials(degree: int, d: Tensor) -> Tensor:
    """`sh_basis` at unit directions d [..., 3] as a gather of monomials and a weighted sum. At degree 3 it issues 23
    operators forward and 50 backward (about half of them views), where the entry-by-entry polynomial issues 55 and
    132 (degree 2: 18 and 38 against 25 and 65; degrees 0 and 1 keep the entries, 7 / 0 and 10 / 25 operators): on a
    GPU each is a launch or at least a dispatch. The CPU keeps the entry form, which its compiled kernels
    mirror. No matrix product, so TF32 cannot touch it. Equal to the entry form up to float rounding
    (tests/test_sh_basis.py)."""
    k, parts = num_sh_bases(degree), [torch.ones_like(d[..., :1]), d]  # [..., 1], [..., 3]
    if degree >= 2:
        squares = (d.unsqueeze(-1) * d.unsqueeze(-2)).flatten(-2)  # [..., 9]
        squares = squares.index_select(-1, constant_on(_SQUARE_PICK, d.device))  # [..., 6]
        parts.append(squares)
        if degree >= 3:
            cubes = (squares.unsqueeze(-1) * d.unsqueeze(-2)).flatten(-2)  # [..., 18]
            parts.append(cubes.index_select(-1, constant_on(_CUBE_PICK, d.device)))  # [..., 10]
    mono = torch.cat(parts, dim=-1)  # [..., 1 + 3 + 6 + 10 up to the degree]
    terms = mono.index_select(-1, constant_on(_TERM_INDEX, d.device)[: 3 * k])  # [..., 3k]
    terms = terms * constant_on(_TERM_COEF, d.device, d.dtype)[: 3 * k]
    return terms.unflatten(-1, (k, 3)).sum(-1)  # [..., k]


def eval_sh(degree: int, coeffs: Tensor, dirs: Tensor, execution: Execution = COMPILED) -> Tensor:
    """SH value per channel: coeffs [..., K, 3] with K >= (degree+1)^2, dirs [..., 3] -> [..., 3].

    Only the first (degree+1)^2 coefficients are used, so a model can raise its active degree during training
    without reallocating its coefficients.
    """
    k = num_sh_bases(degree)
    if coeffs.shape[-2] < k:
        raise ValueError(
            f"sh coefficients: degree {degree} needs at least {k} coefficients along dim -2, found shape "
            f"{tuple(coeffs.shape)}; pass sh_degree <= {int(coeffs.shape[-2] ** 0.5) - 1} or allocate more."
        )
    basis = sh_basis(degree, dirs, execution=execution)  # [..., k]
    return _BasisDot.apply(basis, coeffs[..., :k, :])  # [..., 3]


class _BasisDot(torch.autograd.Function):
    """sum_k basis[..., k] * coeffs[..., k, :] with a hand-written backward (leading dims broadcast).

    Forward is a broadcast product and sum (a batched [1, k] x [k, 3] matmul per Gaussian was measured slower on
    CPU). Backward gets the basis gradient as one batched [k, 3] x [3, 1] product. Autograd's way is a broadcast
    product and a sum over the colour axis, about a third slower on a CPU."""

    @staticmethod
    def forward(ctx, basis: Tensor, coeffs: Tensor) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(basis, coeffs)
        return (basis.unsqueeze(-1) * coeffs).sum(-2)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, Tensor | None]:  # type: ignore[override]
        basis, coeffs = ctx.saved_tensors
        g_basis = g_coeffs = None
        if ctx.needs_input_grad[0]:
            c = coeffs.expand(*grad.shape[:-1], *coeffs.shape[-2:])  # [..., k, 3]
            g_basis = torch.matmul(c, grad.unsqueeze(-1)).squeeze(-1).sum_to_size(basis.shape)
        if ctx.needs_input_grad[1]:
            g_coeffs = (basis.unsqueeze(-1) * grad.unsqueeze(-2)).sum_to_size(coeffs.shape)
        return g_basis, g_coeffs


def eval_sh_in_frames(
    degree: int, coeffs: Tensor, dirs: Tensor, frames: Tensor, execution: Execution = COMPILED
) -> Tensor:
    """SH value of coefficients expressed in per-Gaussian frames: eval_sh(coeffs, frames^T d) [N, 3].

    coeffs [N, K, 3], dirs [N, 3], frames [N, 3, 3] (rotations). Equals eval_sh(degree, rotate_sh(coeffs, frames),
    dirs) (`framework.rig.sh_rotation`) for one camera at a fraction of the cost: one 3x3 product per Gaussian instead
    of rotating 15 coefficients per channel.
    """
    local = (dirs.unsqueeze(-2) @ frames).squeeze(-2)  # [N, 3] = (R^T d)^T
    return eval_sh(degree, coeffs, local, execution)


def view_colour_dc(
    degree: int, coeffs: Tensor, dirs: Tensor, frames: Tensor, execution: Execution = COMPILED
) -> Tensor:
    """The DC coefficients [N, 1, 3] that render, at sh_degree 0, as the view-dependent colour of `eval_sh_in_frames`.

    Why: every backend evaluates SH itself (+0.5, clamp at 0); handing it the colour as a degree-0 coefficient
    keeps the rasterizer contract unchanged, and eval_sh(0, c / SH_C0) = c exactly up to rounding."""
    return (eval_sh_in_frames(degree, coeffs, dirs, frames, execution) / SH_C0).unsqueeze(-2)


def rgb_to_sh0(rgb: Tensor) -> Tensor:
    """DC coefficient whose colour (after the +0.5 offset) is `rgb`."""
    return (rgb - 0.5) / SH_C0


def sh0_to_rgb(sh0: Tensor) -> Tensor:
    """Inverse of `rgb_to_sh0`."""
    return sh0 * SH_C0 + 0.5
