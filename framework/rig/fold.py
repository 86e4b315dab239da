"""Folding joints into their ancestors: fewer joints in the LBS sum and in a pose, the same skinned surface.

Two uses: a body model that ships more bones than a clothed avatar needs (Anny's 104 -> 22, `plugins/body/anny_body`),
and a scene whose training frames leave some joints still (`framework.model.frozen_body`). A folded joint's skinning
weights are added to its nearest kept ancestor; that is exact while the folded joint keeps its rest rotation.

A joint held at a constant rotation C_f that is not the identity is folded by re-basing the rest pose: the new rest
surface is the old one posed with only the constants (T*_k = product of the constant local transforms above k), each
kept joint moves to where its parent's T* puts it, and a kept joint's rotation, given in world-aligned rest axes,
becomes Q R Q^T with Q the rotation of its parent's T* (its axes turned by the frozen rotations above it). Then
T_k(pose) = T~_k(converted pose) T*_k for every joint, so a point skinned to one joint, or to joints that share the same
T*, lands exactly where the full skeleton puts it; a point blended across a frozen joint whose constant is not the
identity (weights on both sides) moves with the blend of the two sides' re-based positions, a small approximation.
"""

from __future__ import annotations

import torch
from torch import Tensor


def fold_skeleton(
    labels: list[str], parents: list[int], keep: tuple[str, ...] | list[str], owner: str = "skeleton"
) -> tuple[list[int], list[int], list[int]]:
    """Fold every joint not in `keep` into its nearest kept ancestor.

    Returns (kept indices in rig order, parents of the kept joints as kept indices, rig -> kept index map [J])."""
    missing = [k for k in keep if k not in labels]
    if missing:
        raise ValueError(f"{owner}: joints {missing} are not in the rig ({len(labels)} joints: {labels[:6]}...).")
    keep_set = set(keep)
    kept = [i for i, name in enumerate(labels) if name in keep_set]
    if not kept or parents[kept[0]] >= 0:
        raise ValueError(f"{owner}: the folded skeleton must keep the root joint '{labels[parents.index(-1)]}'.")
    position = {full: red for red, full in enumerate(kept)}
    to_kept = []
    for i in range(len(labels)):
        j = i
        while j not in position:
            j = parents[j]
        to_kept.append(position[j])
    kept_parents = [-1 if parents[i] < 0 else to_kept[parents[i]] for i in kept]
    return kept, kept_parents, to_kept


def fold_weights(weights: Tensor, to_kept: list[int] | Tensor, num_kept: int) -> Tensor:
    """Skinning weights [..., J] -> [..., num_kept]: each joint's weight added to the kept joint that drives it."""
    index = torch.as_tensor(to_kept, dtype=torch.long, device=weights.device)
    # a product with the [J, K] 0/1 fold matrix: the sums of `index_add` (to float rounding: each term is a weight
    # times 1 or an exact 0), as one GEMM forward and backward, where `index_add` over the last dimension is a strided
    # scatter (a visible share of L_w's forward+backward with frozen joints and F_dw)
    matrix = weights.new_zeros(index.shape[0], num_kept)
    matrix[torch.arange(index.shape[0], device=weights.device), index] = 1.0
    return weights @ matrix


def rebased_joints(constant_transforms: Tensor, rest_joints: Tensor, parents: Tensor | list[int]) -> Tensor:
    """Rest joints [J, 3] moved by their parent's constant-pose transform T*_parent [J, 4, 4] (the root stays)."""
    par = torch.as_tensor(parents, dtype=torch.long, device=rest_joints.device)
    T_par = constant_transforms[par.clamp_min(0)]  # [J, 4, 4]
    moved = (T_par[:, :3, :3] @ rest_joints.unsqueeze(-1)).squeeze(-1) + T_par[:, :3, 3]
    return torch.where((par < 0).unsqueeze(-1), rest_joints, moved)  # [J, 3]


def parent_rotations(constant_transforms: Tensor, parents: Tensor | list[int]) -> Tensor:
    """Q_k [J, 3, 3]: the rotation of joint k's parent under the constant pose (identity at the root). A kept joint's
    axis-angle a becomes Q_k a in the re-based skeleton (Q R(a) Q^T = R(Q a))."""
    par = torch.as_tensor(parents, dtype=torch.long, device=constant_transforms.device)
    Q = constant_transforms[par.clamp_min(0), :3, :3].clone()  # [J, 3, 3]
    Q[par < 0] = torch.eye(3, dtype=Q.dtype, device=Q.device)
    return Q
