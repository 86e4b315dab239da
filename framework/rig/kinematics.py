"""Forward kinematics and linear blend skinning shared by every body model and the deformers.

Convention (SMPL's, and anny's `local-ref` parameterisation): joint k rotates by R(θ_k) about its rest position j_k in
axes aligned with the world at rest, composed along the chain,

    G_k = G_parent(k) @ [R(θ_k) | j_k - j_parent(k)],   G_root = [R(θ_root) | j_root],

and the rest-to-posed skinning transform is T_k = G_k @ translate(-j_k). An identity pose gives T_k = I.
The chain is composed by pointer jumping (`forward_kinematics_rotmat`): log2(depth) batched products for all joints.
"""

from __future__ import annotations

from functools import lru_cache

import torch
from torch import Tensor

from framework.device_constants import constant_on, values_on
from framework.execution import COMPILED, Execution
from framework.geometry import axis_angle_to_rotmat

_HOMOGENEOUS_ROW = torch.tensor([0.0, 0.0, 0.0, 1.0])  # the last row of every 4x4 transform
#: id(parents tensor) -> (the tensor, its version counter, its values): read once, not per call (on a GPU,
#: `.tolist()` copies to the host and waits for the queue)
_parent_tuples: dict[int, tuple[Tensor, int, tuple[int, ...]]] = {}


def _parents_tuple(parents: Tensor | list[int] | tuple[int, ...]) -> tuple[int, ...]:
    """The parent indices as a Python tuple, read from a tensor once per tensor (and again if it is written to)."""
    if not isinstance(parents, Tensor):
        return tuple(int(p) for p in parents)
    hit = _parent_tuples.get(id(parents))
    if hit is None or hit[0] is not parents or hit[1] != parents._version:
        if len(_parent_tuples) > 64:  # bodies come and go (tests, tools): keep the table small
            _parent_tuples.clear()
        hit = _parent_tuples[id(parents)] = (parents, parents._version, tuple(int(p) for p in parents.tolist()))
    return hit[2]


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
    key = _parents_tuple(parents)
    return _levels_cached(key)


@lru_cache(maxsize=64)
def _ancestor_steps(parents: tuple[int, ...]) -> tuple[tuple[int, ...], ...]:
    """Pointer-jumping tables for `forward_kinematics_rotmat`: step s maps every joint to its 2^s-th ancestor, with
    index J standing for "above the root" (an identity transform that maps to itself). ceil(log2(depth)) steps."""
    depth = len(_levels_cached(parents))  # also checks that `parents` is a tree
    J = len(parents)
    ancestor = [p if p >= 0 else J for p in parents] + [J]
    steps = []
    span = 1
    while span < depth:
        steps.append(tuple(ancestor))
        ancestor = [ancestor[a] for a in ancestor]
        span *= 2
    return tuple(steps)


def forward_kinematics_rotmat(rotations: Tensor, joints: Tensor, parents: Tensor | list[int]) -> tuple[Tensor, Tensor]:
    """Like `forward_kinematics` but with local rotation matrices [B, J, 3, 3] instead of axis-angle.

    The chain is composed by pointer jumping: every joint's transform relative to its 2^s-th ancestor comes from one
    gather and one batched 4x4 product per step, so a 10-level chain takes 4 steps for all joints at once (about
    twice as fast as one product per depth level, forward and backward)."""
    B, J = rotations.shape[:2]
    if joints.dim() == 2:
        joints = joints.unsqueeze(0)
    joints = joints.to(rotations.dtype).expand(B, J, 3)  # [B, J, 3]
    key = _parents_tuple(parents)
    if len(key) != J:
        raise ValueError(f"parents has {len(key)} joints but pose has {J}.")
    steps = _ancestor_steps(key)
    dev, dtype = rotations.device, rotations.dtype
    parent_rows = values_on(tuple(p if p >= 0 else J for p in key) + (J,), dev)  # [J + 1]
    padded = torch.cat([joints, joints.new_zeros(B, 1, 3)], dim=1)  # [B, J + 1, 3], row J: the origin
    offsets = padded - padded[:, parent_rows]  # [B, J + 1, 3] = j_k - j_parent (j_root at the root, 0 in row J)
    eye = torch.eye(3, dtype=dtype, device=dev).expand(B, 1, 3, 3)
    bottom = constant_on(_HOMOGENEOUS_ROW, dev, dtype).expand(B, J + 1, 1, 4)
    top = torch.cat([torch.cat([rotations, eye], dim=1), offsets.unsqueeze(-1)], dim=-1)  # [B, J + 1, 3, 4]
    A = torch.cat([top, bottom], dim=-2)  # [B, J + 1, 4, 4] local transforms; row J: the identity
    for ancestor in steps:
        A = A[:, values_on(ancestor, dev)] @ A  # relative to the next 2^s ancestors up
    G = A[:, :J]  # [B, J, 4, 4]
    to_rest = torch.cat([torch.cat([eye.expand(B, J, 3, 3), -joints.unsqueeze(-1)], dim=-1), bottom[:, :J]], dim=-2)
    return G, G @ to_rest  # T = G @ translate(-j)


def forward_kinematics(
    pose: Tensor, joints: Tensor, parents: Tensor | list[int], execution: Execution = COMPILED
) -> tuple[Tensor, Tensor]:
    """pose [B, J, 3] axis-angle, joints [B, J, 3] or [J, 3] rest positions, parents [J] (-1 at the root)
    -> (G [B, J, 4, 4] global joint transforms, T [B, J, 4, 4] rest-to-posed skinning transforms = G @ translate(-j)).

    Differentiable in pose and joints, finite gradients at zero and pi rotations (Rodrigues with a Taylor branch).
    `execution`: which torch form the rotations take (`framework.geometry.few_kernels`)."""
    if pose.dim() != 3 or pose.shape[-1] != 3:
        raise ValueError(f"pose must be [B, J, 3] axis-angle; got shape {tuple(pose.shape)}.")
    return forward_kinematics_rotmat(axis_angle_to_rotmat(pose, execution), joints, parents)


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
