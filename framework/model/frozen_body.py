"""A body with some joints frozen: held at a constant rotation and folded into their nearest kept ancestor.

Why: a joint that does not move over the training frames carries no pose information, yet it costs a column of the
LBS sum for every Gaussian, three inputs of F_a and a row of the pose-refinement tables. Freezing removes it from all
three. The math (re-basing the rest pose on the constant rotations, exact for points skinned within one group) is in
`framework.rig.fold`; this module wraps any `BodyModel` with it. The dataset still delivers full poses: `input_pose`
drops the frozen joints and turns the kept joints' axes into the re-based rest frame.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
from torch import Tensor

from framework.errors import SplatrigError
from framework.interfaces.body import BodyModel
from framework.rig.fold import fold_skeleton, fold_weights, parent_rotations, rebased_joints
from framework.rig.kinematics import skin_points


class FrozenJointsError(SplatrigError):
    """A frozen-joint list that names no joint of the body, or the root."""


class FrozenJointsBody(BodyModel):
    """`base` with the joints in `frozen` held at `frozen[name]` (axis-angle [3], default zero) and folded away."""

    def __init__(self, base: BodyModel, frozen: Sequence[str], constants: Mapping[str, Sequence[float]] | None = None):
        super().__init__()
        names = list(base.joint_names)
        parents = [int(p) for p in base.parents.tolist()]
        unknown = [n for n in frozen if n not in names]
        if unknown:
            raise FrozenJointsError(
                f"scene.frozen_joints: {unknown} are not joints of the {base.pose_description()}; its joints are "
                f"{names}. Name joints from that list or clear the key (scene.frozen_joints=[])."
            )
        root = names[parents.index(-1)]
        if root in frozen:
            raise FrozenJointsError(
                f"scene.frozen_joints: the root joint '{root}' cannot be frozen (there is no parent to fold it into); "
                f"remove it from the list."
            )
        constants = dict(constants or {})
        extra = sorted(set(constants) - set(frozen))
        if extra:
            raise FrozenJointsError(f"frozen-joint constants name joints that are not frozen: {extra}.")
        self.registry_name = base.registry_name
        self._base_description = base.pose_description()
        self.frozen_joints = [n for n in names if n in set(frozen)]
        kept, kept_parents, to_kept = fold_skeleton(names, parents, [n for n in names if n not in set(frozen)])
        dtype = base.rest_vertices.dtype
        constant_pose = torch.zeros(1, len(names), 3, dtype=dtype, device=base.rest_vertices.device)
        for name, value in constants.items():
            constant_pose[0, names.index(name)] = torch.as_tensor(value, dtype=dtype)
        with torch.no_grad():
            T_star = base.bone_transforms(constant_pose)[0]  # [J, 4, 4]
            rest = skin_points(base.rest_vertices, base.skin_weights, T_star[None])[0].to(dtype)  # [V, 3]
            joints = rebased_joints(T_star, base.rest_joints, parents)[kept]  # [J', 3]
            Q = parent_rotations(T_star, parents)[kept]  # [J', 3, 3]
        self.joint_names = [names[i] for i in kept]
        self.register_buffer("rest_vertices", rest.contiguous())  # [V, 3]
        self.register_buffer("faces", base.faces.clone())  # [F, 3]
        self.register_buffer("skin_weights", fold_weights(base.skin_weights, to_kept, len(kept)))  # [V, J']
        self.register_buffer("parents", torch.as_tensor(kept_parents, dtype=torch.long))  # [J']
        self.register_buffer("rest_joints", joints.contiguous())  # [J', 3]
        if base.uvs is not None:
            self.register_buffer("uvs", base.uvs.clone())
        if base.face_uvs is not None:
            self.register_buffer("face_uvs", base.face_uvs.clone())
        # not persistent: derived from the config and the data on every construction
        self.register_buffer("kept_indices", torch.as_tensor(kept, dtype=torch.long), persistent=False)  # [J']
        self.register_buffer("fold_index", torch.as_tensor(to_kept, dtype=torch.long), persistent=False)  # [J]
        self.register_buffer("axis_rotations", Q.contiguous(), persistent=False)  # [J', 3, 3]
        self.register_buffer("constant_pose", constant_pose[0], persistent=False)  # [J, 3]
        self._num_input_joints = len(names)
        self._base = (base,)  # in a tuple: not a submodule, so its buffers stay out of checkpoints

    @property
    def num_input_joints(self) -> int:
        return self._num_input_joints

    @property
    def base_body(self) -> BodyModel:
        """The full skeleton whose poses `input_pose` takes (motion files are retargeted onto it)."""
        return self._base[0]

    @property
    def input_body(self) -> BodyModel:
        return self.base_body

    def unfolded_skinning(self) -> tuple[Tensor, Tensor]:
        """The base body's weights on this body's (re-based) rest vertices, and each joint's kept joint."""
        return self.base_body.skin_weights.to(self.skin_weights.device), self.fold_index

    def pose_description(self) -> str:
        return f"{self._base_description} with {len(self.frozen_joints)} frozen joints ({self.num_joints} left)"

    def input_pose(self, pose: Tensor) -> Tensor:
        """[B, J, 3] dataset pose -> [B, J', 3]: kept joints only, axes turned into the re-based rest frame."""
        if pose.dim() != 3 or pose.shape[1] != self._num_input_joints:
            raise ValueError(
                f"{self.pose_description()}: the input pose must be [B, {self._num_input_joints}, 3]; "
                f"got {tuple(pose.shape)}."
            )
        kept = pose.index_select(1, self.kept_indices)  # [B, J', 3]
        return (self.axis_rotations.to(pose.dtype) @ kept.unsqueeze(-1)).squeeze(-1)

    def full_pose(self, pose: Tensor) -> Tensor:
        """The inverse of `input_pose`: [B, J', 3] -> [B, J, 3] with the frozen joints at their constants."""
        full = self.constant_pose.to(pose.dtype).expand(pose.shape[0], -1, -1).clone()
        full[:, self.kept_indices] = (self.axis_rotations.transpose(-1, -2).to(pose.dtype) @ pose.unsqueeze(-1))[..., 0]
        return full


def frozen_constants(poses: Tensor, joint_names: Sequence[str], frozen: Sequence[str]) -> dict[str, list[float]]:
    """The rotation each frozen joint is held at: the mean of its training rotations (poses [F, J, 3] axis-angle),
    as axis-angle lists (they go into the run's saved `data_info`, so a checkpoint rebuilds the same body)."""
    from scipy.spatial.transform import Rotation

    names = list(joint_names)
    out = {}
    for name in frozen:
        if name in names:
            rotvecs = poses[:, names.index(name)].detach().double().cpu().numpy()  # [F, 3]
            out[name] = [float(x) for x in Rotation.from_rotvec(rotvecs).mean().as_rotvec()]
    return out
