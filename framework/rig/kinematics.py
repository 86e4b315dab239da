"""Forward kinematics and linear blend skinning shared by every body model and the deformers.

Convention (SMPL's, and anny's `local-ref` parameterisation): joint k rotates by R(θ_k) about its rest position j_k in
axes aligned with the world at rest, composed along the chain,

    G_k = G_parent(k) @ [R(θ_k) | j_k - j_parent(k)],   G_root = [R(θ_root) | j_root],

and the rest-to-posed skinning transform is T_k = G_k @ translate(-j_k). An identity pose gives T_k = I.
The chain is evaluated one depth level at a time (all joints whose parents are already posed in one batched product),
so a 104-joint rig costs ~15 small matmuls instead of 104 Python iterations.
"""

from __future__ import annotations

from functools import lru_cache

import torch
from torch import Tensor

from framework.geometry import axis_angle_to_rotmat


@lru_cache(maxsize=64)
def _levels_cached(parents: tuple[int, ...]) -> tuple[tuple[tuple[int, ...], tuple[int, ...]], ...]:
    children: list[list[int]] = [[] for _ in parents]
    roots = []
    for k, p in enumerate(parents):
        if p < 0:
            roots.append(k)
        elif not 0 <= p < len(parents):
            raise ValueError(f"parents[{k}] = {p} is not a joint index (expected -1 or 0..{len(parents) - 1}).")
        else:
            children[p].append(k)
    if len(roots) != 1:
        raise ValueError(f"parents must have exactly one root (-1); found {len(roots)} at {roots}.")
    levels: list[tuple[tuple[int, ...], tuple[int, ...]]] = []
    current = roots
    seen = len(current)
    levels.append((tuple(current), ()))
    while True:
        nxt: list[int] = []
        local: list[int] = []  # each child's parent position within the previous level
        for pos, j in enumerate(current):
            for c in children[j]:
                nxt.append(c)
                local.append(pos)
        if not nxt:
            break
        seen += len(nxt)
        levels.append((tuple(nxt), tuple(local)))
        current = nxt
    if seen != len(parents):
        raise ValueError(f"parents do not form a tree: only {seen} of {len(parents)} joints descend from the root.")
    return tuple(levels)


def kinematic_levels(parents: Tensor | list[int]) -> tuple[tuple[tuple[int, ...], tuple[int, ...]], ...]:
    """Depth levels of a tree: ((joint ids), (parent position within the previous level)) per level, root first."""
    key = tuple(int(p) for p in (parents.tolist() if isinstance(parents, Tensor) else parents))
    return _levels_cached(key)


def _rigid(rot: Tensor, trans: Tensor) -> Tensor:
    """[..., 3, 3], [..., 3] -> [..., 4, 4]."""
    top = torch.cat([rot, trans.unsqueeze(-1)], dim=-1)  # [..., 3, 4]
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


def forward_kinematics_rotmat(rotations: Tensor, joints: Tensor, parents: Tensor | list[int]) -> tuple[Tensor, Tensor]:
    """Like `forward_kinematics` but with local rotation matrices [B, J, 3, 3] instead of axis-angle."""
    B, J = rotations.shape[:2]
    if joints.dim() == 2:
        joints = joints.unsqueeze(0)
    joints = joints.to(rotations.dtype).expand(B, J, 3)  # [B, J, 3]
    levels = kinematic_levels(parents)
    if sum(len(ids) for ids, _ in levels) != J:
        raise ValueError(f"parents has {sum(len(i) for i, _ in levels)} joints but pose has {J}.")
    par = torch.as_tensor([int(p) for p in (parents.tolist() if isinstance(parents, Tensor) else parents)])
    par = par.clamp_min(0).to(joints.device)
    offsets = joints - joints[:, par]  # [B, J, 3]; the root's row is replaced below

    order: list[int] = []
    A_levels: list[Tensor] = []  # accumulated world rotations per level [B, L, 3, 3]
    w_levels: list[Tensor] = []  # posed joint positions per level [B, L, 3]
    for depth, (ids, local) in enumerate(levels):
        idx = torch.as_tensor(ids, device=joints.device)
        R = rotations[:, idx]  # [B, L, 3, 3]
        if depth == 0:
            A, w = R, joints[:, idx]
        else:
            loc = torch.as_tensor(local, device=joints.device)
            A_p, w_p = A_levels[-1][:, loc], w_levels[-1][:, loc]  # [B, L, 3, 3], [B, L, 3]
            A = A_p @ R
            w = w_p + (A_p @ offsets[:, idx].unsqueeze(-1)).squeeze(-1)
        order.extend(ids)
        A_levels.append(A)
        w_levels.append(w)
    inverse = torch.empty(J, dtype=torch.long)
    inverse[torch.as_tensor(order)] = torch.arange(J)
    inverse = inverse.to(joints.device)
    A = torch.cat(A_levels, dim=1)[:, inverse]  # [B, J, 3, 3]
    w = torch.cat(w_levels, dim=1)[:, inverse]  # [B, J, 3]
    G = _rigid(A, w)  # [B, J, 4, 4]
    T = _rigid(A, w - (A @ joints.unsqueeze(-1)).squeeze(-1))  # [B, J, 4, 4] = G @ translate(-j)
    return G, T


def forward_kinematics(pose: Tensor, joints: Tensor, parents: Tensor | list[int]) -> tuple[Tensor, Tensor]:
    """pose [B, J, 3] axis-angle, joints [B, J, 3] or [J, 3] rest positions, parents [J] (-1 at the root)
    -> (G [B, J, 4, 4] global joint transforms, T [B, J, 4, 4] rest-to-posed skinning transforms = G @ translate(-j)).

    Differentiable in pose and joints, finite gradients at zero and pi rotations (Rodrigues with a Taylor branch)."""
    if pose.dim() != 3 or pose.shape[-1] != 3:
        raise ValueError(f"pose must be [B, J, 3] axis-angle; got shape {tuple(pose.shape)}.")
    return forward_kinematics_rotmat(axis_angle_to_rotmat(pose), joints, parents)


def blend_transforms(weights: Tensor, transforms: Tensor) -> Tensor:
    """weights [N, J] or [B, N, J], transforms [B, J, 4, 4] -> per-point blended [B, N, 3, 4] (the top rows only;
    the bottom row of a blend of rigid transforms with weights summing to one is always [0, 0, 0, 1])."""
    top = transforms[..., :3, :].to(transforms.dtype)  # [B, J, 3, 4]
    w = weights.to(top.dtype)
    if w.dim() == 2:
        return torch.einsum("nj,bjrc->bnrc", w, top)
    return torch.einsum("bnj,bjrc->bnrc", w, top)


def skin_points(points: Tensor, weights: Tensor, transforms: Tensor) -> Tensor:
    """Linear blend skinning: points [N, 3] or [B, N, 3], weights [N, J] or [B, N, J], transforms [B, J, 4, 4]
    -> [B, N, 3] in the dtype of `transforms`."""
    M = blend_transforms(weights, transforms)  # [B, N, 3, 4]
    p = points.to(M.dtype)
    if p.dim() == 2:
        p = p.unsqueeze(0)
    return (M[..., :3] @ p.unsqueeze(-1)).squeeze(-1) + M[..., 3]  # [B, N, 3]
