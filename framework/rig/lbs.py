"""Linear blend skinning of Gaussians: blend bone transforms, split off the rotation, pose every attribute.

Per Gaussian i, P_i = sum_k w_ik P_k = [A_i | t_i]. The polar decomposition A_i = R_i S_i (`framework.rig.polar`) gives
the rotation R_i and a symmetric stretch S_i (identity for a rigid blend; < 1 across a bent joint, the "candy
wrapper"). Decisions:
- means' = A_i x + t_i (centres="blended", ours): the exact LBS position, so Gaussians follow the skinned mesh
  exactly. centres="rigid" is the paper's eq. 4, R_i x + t_i: the centre moves by the rotation part only, so across a
  bent joint it does not shrink towards the bone with the mesh.
- quats' = quat(R_i) * q / |q|: the Gaussian's axes rotate with R_i.
- scale: with stretch="diag", the Gaussian's scales are multiplied by the diagonal of S_i expressed in the Gaussian's
  own frame, k_l = a_l^T S_i a_l (a_l = its l-th axis). This is the "scale" part of P_i; the off-diagonal (shear)
  part is dropped, as the paper does. stretch="none" keeps the canonical scales (rotation + translation only).
- SH degrees >= 1 are rotated by R_i (`framework.rig.sh_rotation`), so view-dependent colour turns with the body.
  `lbs_with_sh_frames` instead leaves the coefficients canonical and returns R_i: a renderer of one camera then
  evaluates the colour at R_i^T d (`framework.splat.sh.eval_sh_in_frames`), which is the same colour
  (eval(rotate_sh(c, R), d) = eval(c, R^T d)) without rotating 15 coefficients per Gaussian.
"""

from __future__ import annotations

import torch
from torch import Tensor

from framework.execution import COMPILED, Execution
from framework.geometry import (
    products_3x3,
    quat_multiply,
    quat_normalize,
    quat_to_rotmat,
    quat_to_rotmat_entry_major,
    rotmat_to_quat_entry_major,
)
from framework.guards import LBS_MIN_STRETCH, WEIGHT_VAR_MIN
from framework.rig.polar import polar_rotation_entry_major
from framework.rig.sh_rotation import rotate_sh
from framework.types import Gaussians

STRETCH_MODES = ("diag", "none")
POLAR_DTYPES = {"float32": torch.float32, "float64": torch.float64}
CENTRE_MODES = ("blended", "rigid")


def blended_affine(weights: Tensor, transforms: Tensor) -> tuple[Tensor, Tensor]:
    """weights [N, J], transforms [J, 4, 4] -> A [3, 3, N], t [3, N] of P_i = sum_k w_ik P_k, entry-major.

    Why entry-major: each later step (the polar iteration, the products with the Gaussians' means and axes) is then
    a few vector operations over N contiguous values, where [N, 3, 3] batches run N tiny 3x3 products."""
    J = transforms.shape[0]
    if weights.shape[-1] != J:
        raise ValueError(
            f"lbs: blend weights have {weights.shape[-1]} joints but bone_transforms has {J}; the deformer must be "
            "bound to the body whose transforms it receives."
        )
    P = (transforms[:, :3, :].reshape(J, 12).t().to(weights.dtype) @ weights.t()).view(3, 4, -1)  # [3, 4, N]
    return P[:, :3], P[:, 3]


def _rotations(A: Tensor, dtype: torch.dtype | None, execution: Execution) -> tuple[Tensor, Tensor]:
    """A [3, 3, N] -> R [3, 3, N] of A = R S and its quaternions [4, N]."""
    N = A.shape[-1]
    R = polar_rotation_entry_major(A.reshape(9, N), dtype, execution)  # [9, N]
    return R.view(3, 3, N), rotmat_to_quat_entry_major(R)


def apply_lbs(
    gaussians: Gaussians,
    weights: Tensor,
    transforms: Tensor,
    stretch: str = "diag",
    polar_dtype: torch.dtype | None = None,
    centres: str = "blended",
    execution: Execution = COMPILED,
) -> Gaussians:
    """Pose canonical Gaussians with blend weights [N, J] and rest-to-posed transforms [J, 4, 4], SH rotated.

    `polar_dtype`: the least precision of the polar decomposition's iteration (float64 inputs always iterate in float64;
    default: the inputs' dtype; see framework.rig.polar). `centres`: blended moves centres by A x + t (exact LBS),
    rigid by R x + t (the paper's eq. 4). `execution`: which torch forms the rotation helpers take."""
    posed, R = lbs_with_sh_frames(gaussians, weights, transforms, stretch, polar_dtype, centres, execution)
    return posed.replace(sh=rotate_sh(posed.sh, R, execution))


def lbs_with_sh_frames(
    gaussians: Gaussians,
    weights: Tensor,
    transforms: Tensor,
    stretch: str = "diag",
    polar_dtype: torch.dtype | None = None,
    centres: str = "blended",
    execution: Execution = COMPILED,
) -> tuple[Gaussians, Tensor]:
    """`apply_lbs` without the SH rotation: (posed Gaussians whose SH is still canonical, R [N, 3, 3])."""
    if stretch not in STRETCH_MODES:
        raise ValueError(f"lbs: stretch must be one of {STRETCH_MODES}, got '{stretch}'.")
    if centres not in CENTRE_MODES:
        raise ValueError(f"lbs: centres must be one of {CENTRE_MODES}, got '{centres}'.")
    A, t = blended_affine(weights, transforms)  # [3, 3, N], [3, N]
    R, qR = _rotations(A, None if polar_dtype is None else torch.promote_types(A.dtype, polar_dtype), execution)
    moves = A if centres == "blended" else R
    means = ((moves * gaussians.means.t().unsqueeze(0)).sum(1) + t).t().contiguous()  # [N, 3]
    q = gaussians.quats.t().contiguous()  # [4, N]
    # normalised first: a quaternion below NORM_EPS means the identity, and the product must still turn with R
    unit = quat_normalize(q, dim=0, execution=execution)  # [4, N]
    quats = quat_multiply(qR, unit, dim=0, execution=execution).t().contiguous()  # [N, 4]
    log_scales = gaussians.log_scales
    if stretch == "diag":
        Q = quat_to_rotmat_entry_major(q, execution).view(3, 3, -1)  # [3, 3, N], columns = the Gaussian's axes
        # k_l = a_l^T S a_l with S = sym(R^T A): a quadratic form sees only the symmetric part, so R^T A will do
        k = (Q * products_3x3(products_3x3(R, A, transpose_x=True), Q)).sum(0)  # [3, N]
        log_scales = log_scales + torch.log(k.clamp_min(LBS_MIN_STRETCH)).t()  # [N, 3]
    return gaussians.replace(means=means, quats=quats, log_scales=log_scales), R.permute(2, 0, 1)


def six_points(gaussians: Gaussians, execution: Execution = COMPILED) -> Tensor:
    """The six points x +- s_l a_l along each Gaussian axis, [N, 6, 3] (the L_w sampling pattern)."""
    Q = quat_to_rotmat(gaussians.quats, execution)  # [N, 3, 3]
    axes = Q * gaussians.scales.unsqueeze(-2)  # [N, 3, 3], column l = s_l a_l
    offsets = torch.cat([axes, -axes], dim=-1).transpose(-1, -2)  # [N, 6, 3]
    return gaussians.means.unsqueeze(-2) + offsets


def weight_std(weights6: Tensor) -> Tensor:
    """[N, 6, J] weights at the six points -> [N]: per-joint std over the six points, summed over joints.

    Summing (not averaging) over joints keeps the value independent of how many joints a skeleton has far away."""
    # two-pass variance (Tensor.var over a middle dim was measured 3x slower on CPU, forward+backward)
    var = (weights6 - weights6.mean(dim=-2, keepdim=True)).square().mean(dim=-2)  # [N, J]
    tiny = WEIGHT_VAR_MIN
    # sqrt has an infinite slope at 0 (rigid regions have var = 0 exactly): mask it so gradients stay finite.
    std = torch.where(var > tiny, torch.sqrt(torch.where(var > tiny, var, torch.ones_like(var))), torch.zeros_like(var))
    return std.sum(-1)
