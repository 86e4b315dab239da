"""Posable body models: skeleton, skinning weights, surface, forward kinematics."""

from __future__ import annotations

from abc import ABC

import torch
from torch import Tensor, nn

from framework.execution import ExecutionMixin
from framework.rig.kinematics import forward_kinematics, skin_points


class BodyModel(nn.Module, ExecutionMixin, ABC):
    """A skinned body in its rest pose.

    Buffers every body provides (float32 unless stated):
      rest_vertices [V, 3], faces [F, 3] long, skin_weights [V, J] (rows sum to 1),
      parents [J] long (-1 for the root), rest_joints [J, 3].
    Optional: uvs [Vt, 2] and face_uvs [F, 3] long (texture coordinates and each face's indices into them).
    `joint_names` lists the J joints in order.
    Pose convention: `pose` [B, J, 3] axis-angle rotations, joint k rotating about its rest joint position in axes
    aligned with the world at rest, composed along the kinematic chain (SMPL's convention); joint 0 is the root.
    """

    registry_name: str = ""
    rest_vertices: Tensor  # [V, 3]
    faces: Tensor  # [F, 3] long
    skin_weights: Tensor  # [V, J]
    parents: Tensor  # [J] long
    rest_joints: Tensor  # [J, 3]
    joint_names: list[str]
    # Joints whose rotations are F_a's pose input, in order (None: every joint). A body with many small joints
    # (SMPL-X's fingers and eyes) narrows it so the corrector sees the pose that changes the clothing's appearance.
    pose_input_joints: list[int] | None = None

    def __init__(self) -> None:
        super().__init__()
        # The optional buffers, declared here as None so every body has them (a body with texture coordinates
        # registers them again with its tensors).
        self.register_buffer("uvs", None)  # [Vt, 2]
        self.register_buffer("face_uvs", None)  # [F, 3] long

    @property
    def num_joints(self) -> int:
        return int(self.parents.shape[0])

    @property
    def num_pose_features(self) -> int:
        """Length of `pose_features`: 3 per pose-input joint."""
        return 3 * (self.num_joints if self.pose_input_joints is None else len(self.pose_input_joints))

    def pose_features(self, pose: Tensor) -> Tensor:
        """pose [B, J, 3] -> [B, num_pose_features]: the axis-angle rotations of the pose-input joints, flattened."""
        if self.pose_input_joints is not None:
            pose = pose[:, self.pose_input_joints]
        return pose.reshape(pose.shape[0], -1)

    @property
    def num_input_joints(self) -> int:
        """Joints of the poses this body is driven with (the dataset's); more than `num_joints` when joints are
        folded away (`framework.model.frozen_body`)."""
        return self.num_joints

    @property
    def input_body(self) -> BodyModel:
        """The body whose skeleton dataset poses and motion files are given for: this one, or the full body a body
        with frozen joints folded (`framework.model.frozen_body`)."""
        return self

    def input_pose(self, pose: Tensor) -> Tensor:
        """A dataset pose [B, num_input_joints, 3] -> this body's pose [B, J, 3] (the same pose for most bodies)."""
        return pose

    def unfolded_skinning(self) -> tuple[Tensor, Tensor] | None:
        """(skin weights [V, J_full] over every joint of the skeleton this body folded, joint -> kept-joint index
        [J_full]) for a body with frozen joints folded away (`framework.model.frozen_body`), else None.

        Why: the paper's L_w (the std of the blend weights over the six points x +- s_l a_l) is defined on the whole
        skeleton. Folded weights are constant across a boundary between two folded joints, so measured on them L_w
        stops holding Gaussians back from spreading over it (a near-static scene with 18 of 22 joints frozen trained
        Gaussians twice as wide and 0.5 dB worse at 4000 steps; docs/results/scene_adaptive.md)."""
        return None

    def pose_description(self) -> str:
        """How this body names itself in a pose-shape error (subclasses add what helps the user fix the pose)."""
        return f"{self.registry_name or type(self).__name__} body"

    def bone_transforms(self, pose: Tensor, joints: Tensor | None = None) -> Tensor:
        """pose [B, J, 3], joints [B, J, 3] or None (rest joints) -> [B, J, 4, 4] rest-to-posed skinning transforms
        (G_k @ translate(-j_k)), differentiable in pose and joints. Every body poses its skeleton the same way
        (SMPL's convention, see the class docstring); bodies differ in their rest shape, not in kinematics."""
        if pose.dim() != 3 or pose.shape[1:] != (self.num_joints, 3):
            raise ValueError(
                f"{self.pose_description()}: pose must be [B, {self.num_joints}, 3] axis-angle; "
                f"got {tuple(pose.shape)}."
            )
        joints = self.rest_joints if joints is None else joints
        return forward_kinematics(pose, joints, self.parents, self.execution)[1]

    def posed_vertices(self, pose: Tensor, joints: Tensor | None = None) -> Tensor:
        """Linear blend skinning of the rest mesh, [B, V, 3]."""
        return skin_points(self.rest_vertices, self.skin_weights, self.bone_transforms(pose, joints))

    def vertex_normals(self, vertices: Tensor | None = None) -> Tensor:
        """Area-weighted unit vertex normals [V, 3] of the rest mesh, or of `vertices` [..., V, 3] (e.g. posed)."""
        v = self.rest_vertices if vertices is None else vertices
        f = self.faces
        a, b, c = v[..., f[:, 0], :], v[..., f[:, 1], :], v[..., f[:, 2], :]  # [..., F, 3]
        face_n = torch.linalg.cross(b - a, c - a, dim=-1)  # [..., F, 3], length = 2 * area
        n = torch.zeros_like(v)
        for k in range(3):
            n = n.index_add(-2, f[:, k], face_n)
        return n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)

    def surface_samples(self, n: int, seed: int = 0) -> tuple[Tensor, Tensor, Tensor]:
        """`n` area-weighted random points on the rest mesh, deterministic for `seed`.

        Returns points [n, 3], face ids [n] long and barycentric coordinates [n, 3] (points = bary @ face corners),
        so callers can interpolate any per-vertex quantity (skinning weights, UVs, normals) at the samples."""
        v, f = self.rest_vertices.double(), self.faces
        a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]  # [F, 3]
        area = 0.5 * torch.linalg.cross(b - a, c - a, dim=-1).norm(dim=-1)  # [F]
        gen = torch.Generator(device="cpu").manual_seed(int(seed))
        cdf = torch.cumsum(area.cpu(), 0)  # inverse-CDF sampling: handles n = 0 and any face count
        u = torch.rand(int(n), generator=gen, dtype=torch.float64) * cdf[-1]
        face_ids = torch.searchsorted(cdf, u, right=True).clamp_max(len(cdf) - 1)  # [n]
        r1, r2 = torch.rand(2, int(n), generator=gen, dtype=torch.float64)
        s = r1.sqrt()  # uniform on a triangle (Osada et al.)
        bary = torch.stack([1 - s, s * (1 - r2), s * r2], dim=-1)  # [n, 3]
        face_ids = face_ids.to(f.device)
        corners = v[f[face_ids]]  # [n, 3, 3]
        points = (bary.to(v.device).unsqueeze(-1) * corners).sum(-2)
        dtype = self.rest_vertices.dtype
        return points.to(dtype), face_ids, bary.to(device=v.device, dtype=dtype)
