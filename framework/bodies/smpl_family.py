"""SMPL and SMPL-X loaded through `smplx` from a model file the user supplies (shared by `body=smpl` and `body=smplx`).

The model files are not redistributable (their licence forbids it), so nothing is shipped or downloaded: the user
registers at https://smpl.is.tue.mpg.de (SMPL) or https://smpl-x.is.tue.mpg.de (SMPL-X) and points
`body.model_path` at the file (`SMPL_NEUTRAL.pkl`, `SMPLX_NEUTRAL.npz`, ...) or at the folder holding it.

The body is fixed at construction for the given `betas`: rest vertices = v_template + shapedirs · betas, rest joints
= J_regressor @ rest vertices (SMPL's own joint regression), skinning weights and parents (from `kintree_table`) as
in the file. `bone_transforms` is our forward kinematics, identical to smplx's `batch_rigid_transform`.

Pose blend shapes: smplx's posed mesh adds pose-dependent correctives (posedirs · (R(θ) - I)) before skinning.
Gaussians deformed by LBS cannot follow those offsets, so by default (`pose_blendshapes=False`) `posed_vertices` is
pure LBS of the rest mesh; it then differs from smplx's output by exactly the corrective offsets (a few millimetres
for real SMPL poses). With `pose_blendshapes=True` it reproduces smplx's vertices (tests/test_body_smpl.py checks
both), while `bone_transforms` is unchanged.

SMPL-X poses are absolute joint rotations (smplx's `flat_hand_mean=True`, EasyMocap's `use_flat_mean`): no mean hand
pose is added. Expression coefficients change the face before skinning; a body fixed at construction has none.
"""

from __future__ import annotations

import contextlib
import io

import torch
from torch import Tensor

from framework.bodies.model_files import resolve_model_file
from framework.geometry import axis_angle_to_rotmat
from framework.interfaces.body import BodyModel
from framework.rig.kinematics import skin_points

SMPL_JOINT_NAMES = [
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_hand",
    "right_hand",
]


class SmplFamilyBody(BodyModel):
    """SMPL (24 joints) or SMPL-X (55 joints) with fixed shape `betas`; see the module docstring."""

    def __init__(
        self,
        model_path: str | None = None,
        model_type: str = "smpl",
        gender: str = "neutral",
        betas: list[float] | None = None,
        num_betas: int = 10,
        pose_blendshapes: bool = False,
    ) -> None:
        super().__init__()
        path = resolve_model_file(model_path, model_type, gender)
        import smplx  # lazy: only needed to read the file

        kwargs = dict(gender=gender, num_betas=num_betas, dtype=torch.float64)
        with contextlib.redirect_stdout(io.StringIO()):  # smplx prints a notice for 10-component SMPL-X files
            if model_type == "smpl":
                model = smplx.SMPL(model_path=str(path), **kwargs)
            else:
                model = smplx.SMPLX(
                    model_path=str(path), ext=path.suffix[1:], use_pca=False, flat_hand_mean=True, **kwargs
                )
        n_betas = model.shapedirs.shape[-1]
        b = torch.zeros(n_betas, dtype=torch.float64)
        if betas is not None:
            if len(betas) > n_betas:
                raise ValueError(
                    f"{model_type} body: {len(betas)} betas given but {path.name} has {n_betas} shape components."
                )
            b[: len(betas)] = torch.as_tensor(list(betas), dtype=torch.float64)
        with torch.no_grad():
            v_shaped = model.v_template + torch.einsum("vcl,l->vc", model.shapedirs, b)  # [V, 3]
            joints = model.J_regressor @ v_shaped  # [J, 3]
        J = joints.shape[0]
        self.model_type = model_type
        self.model_file = str(path)
        self.pose_blendshapes = bool(pose_blendshapes)
        if J == len(SMPL_JOINT_NAMES):
            self.joint_names = list(SMPL_JOINT_NAMES)
        else:
            self.joint_names = [f"joint_{k:02d}" for k in range(J)]
        f32 = torch.float32
        self.register_buffer("rest_vertices", v_shaped.to(f32))  # [V, 3]
        self.register_buffer("faces", torch.as_tensor(model.faces_tensor, dtype=torch.long))  # [F, 3]
        self.register_buffer("skin_weights", model.lbs_weights.to(f32))  # [V, J]
        self.register_buffer("parents", model.parents.clone().long())  # [J]
        self.register_buffer("rest_joints", joints.to(f32))  # [J, 3]
        self.register_buffer("betas", b.to(f32))  # [n_betas]
        # [(J-1)*9, V*3] pose corrective basis; only kept when used
        self.register_buffer("posedirs", model.posedirs.to(f32) if self.pose_blendshapes else None)

    def pose_description(self) -> str:
        name = self.registry_name or self.model_type
        return f"{name} body ({self.model_type.upper()} has {self.num_joints} joints, root first)"

    def posed_vertices(self, pose: Tensor, joints: Tensor | None = None) -> Tensor:
        """LBS of the rest mesh [B, V, 3]; adds smplx's pose correctives first when `pose_blendshapes` is on."""
        T = self.bone_transforms(pose, joints)  # [B, J, 4, 4]
        v = self.rest_vertices.to(T.dtype)  # [V, 3]
        if self.posedirs is not None:
            R = axis_angle_to_rotmat(pose, self.execution)[:, 1:]  # [B, J-1, 3, 3]
            feature = (R - torch.eye(3, dtype=R.dtype, device=R.device)).flatten(1)  # [B, (J-1)*9]
            v = v + (feature @ self.posedirs.to(T.dtype)).view(pose.shape[0], -1, 3)  # [B, V, 3]
        return skin_points(v, self.skin_weights, T)
