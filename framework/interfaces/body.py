"""Posable body models: skeleton, skinning weights, surface, forward kinematics."""

from __future__ import annotations

from abc import ABC, abstractmethod

import torch
from torch import Tensor, nn


class BodyModel(nn.Module, ABC):
    """A skinned body in its rest pose.

    Buffers every body provides (float32 unless stated):
      rest_vertices [V, 3], faces [F, 3] long, skin_weights [V, J] (rows sum to 1),
      parents [J] long (-1 for the root), rest_joints [J, 3].
    `joint_names` lists the J joints in order.
    Pose convention: `pose` [B, J, 3] axis-angle rotations, joint k rotating about its rest joint position in axes
    aligned with the world at rest, composed along the kinematic chain (SMPL's convention); joint 0 is the root.
    """

    registry_name: str = ""
    joint_names: list[str]

    @property
    def num_joints(self) -> int:
        return int(self.parents.shape[0])

    @abstractmethod
    def bone_transforms(self, pose: Tensor, joints: Tensor | None = None) -> Tensor:
        """pose [B, J, 3], joints [B, J, 3] or None (rest joints) -> [B, J, 4, 4] rest-to-posed skinning transforms
        (G_k @ translate(-j_k)), differentiable in pose and joints."""

    def posed_vertices(self, pose: Tensor, joints: Tensor | None = None) -> Tensor:
        """Linear blend skinning of the rest mesh, [B, V, 3]."""
        T = self.bone_transforms(pose, joints)  # [B, J, 4, 4]
        blended = torch.einsum("vj,bjkl->bvkl", self.skin_weights.to(T.dtype), T)  # [B, V, 4, 4]
        v = self.rest_vertices.to(T.dtype)
        return (blended[..., :3, :3] @ v.unsqueeze(-1)).squeeze(-1) + blended[..., :3, 3]
