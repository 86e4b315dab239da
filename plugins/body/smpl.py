"""`smpl`: SMPL or SMPL-X loaded through `smplx` from a model file the user supplies.

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
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import torch
from torch import Tensor

from framework.geometry import axis_angle_to_rotmat
from framework.interfaces.body import BodyModel
from framework.registry import register
from framework.rig.kinematics import skin_points

SMPL_JOINT_NAMES = [
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2", "left_ankle", "right_ankle",
    "spine3", "left_foot", "right_foot", "neck", "left_collar", "right_collar", "head", "left_shoulder",
    "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_hand", "right_hand",
]  # fmt: skip

LICENSORS = {"smpl": "https://smpl.is.tue.mpg.de", "smplx": "https://smpl-x.is.tue.mpg.de"}


def _requires() -> str | None:
    if importlib.util.find_spec("smplx") is None:
        return "the `smplx` package is not installed (pip install smplx)"
    return None


def expected_filename(model_type: str, gender: str, ext: str | None = None) -> str:
    prefix = {"smpl": "SMPL", "smplx": "SMPLX"}[model_type]
    ext = ext or ("pkl" if model_type == "smpl" else "npz")
    return f"{prefix}_{gender.upper()}.{ext}"


def resolve_model_file(model_path: str | Path | None, model_type: str = "smpl", gender: str = "neutral") -> Path:
    """The model file for `model_path` (a file, or a folder holding it directly or under `<model_type>/`).

    Raises FileNotFoundError naming the expected file, every path tried, and where to obtain it."""
    if model_type not in LICENSORS:
        raise ValueError(f"smpl body: model_type must be one of {sorted(LICENSORS)}; got {model_type!r}.")
    if gender.lower() not in ("neutral", "male", "female"):
        raise ValueError(f"smpl body: gender must be neutral, male or female; got {gender!r}.")
    names = [expected_filename(model_type, gender)]
    if model_type == "smplx":
        names.append(expected_filename(model_type, gender, "pkl"))
    tried: list[Path] = []
    if model_path not in (None, ""):
        path = Path(str(model_path)).expanduser()
        if path.suffix in (".pkl", ".npz"):
            tried.append(path)
        else:
            tried += [path / n for n in names] + [path / model_type / n for n in names]
    for candidate in tried:
        if candidate.is_file():
            return candidate
    where = ", ".join(f"'{p}'" for p in tried) if tried else "nowhere (body.model_path is not set)"
    raise FileNotFoundError(
        f"smpl body: the {model_type.upper()} model file '{names[0]}' was not found; tried {where}. "
        f"Its licence forbids redistribution, so it is not shipped with splatrig: register with its licensor at "
        f"{LICENSORS[model_type]}, download the model, and pass body.model_path=/path/to/{names[0]} "
        f"(or the folder that holds it)."
    )


@register("body", "smpl", requires=_requires)
class SMPLBody(BodyModel):
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
        if model_type == "smpl":
            model = smplx.SMPL(model_path=str(path), **kwargs)
        else:
            model = smplx.SMPLX(model_path=str(path), ext=path.suffix[1:], use_pca=False, **kwargs)
        n_betas = model.shapedirs.shape[-1]
        b = torch.zeros(n_betas, dtype=torch.float64)
        if betas is not None:
            if len(betas) > n_betas:
                raise ValueError(f"smpl body: {len(betas)} betas given but {path.name} has {n_betas} shape components.")
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
        return f"smpl body ({self.model_type.upper()} has {self.num_joints} joints, root first)"

    def posed_vertices(self, pose: Tensor, joints: Tensor | None = None) -> Tensor:
        """LBS of the rest mesh [B, V, 3]; adds smplx's pose correctives first when `pose_blendshapes` is on."""
        T = self.bone_transforms(pose, joints)  # [B, J, 4, 4]
        v = self.rest_vertices.to(T.dtype)  # [V, 3]
        if self.posedirs is not None:
            R = axis_angle_to_rotmat(pose)[:, 1:]  # [B, J-1, 3, 3]
            feature = (R - torch.eye(3, dtype=R.dtype, device=R.device)).flatten(1)  # [B, (J-1)*9]
            v = v + (feature @ self.posedirs.to(T.dtype)).view(pose.shape[0], -1, 3)  # [B, V, 3]
        return skin_points(v, self.skin_weights, T)
