"""The animatable package of a loaded avatar for a motion (layout and posing formula: framework.formats.animatable)."""

from __future__ import annotations

import numpy as np
import torch
from tqdm.auto import tqdm

from framework.animation.frames import frame_batch, point_camera
from framework.data.motion_files import Motion
from framework.errors import SplatrigError
from framework.formats.animatable import AnimatablePackage

CORRECTED_FIELDS = ("opacity_logits", "log_scales", "quats", "sh")  # what a corrector may change


@torch.no_grad()
def animatable_package(module, motion: Motion, frames: list[int], corrections: bool = True) -> AnimatablePackage:
    """Canonical Gaussians, their final blend weights (baked now if the checkpoint has none), the refined skeleton and
    every frame's bone transforms; with `corrections`, the corrector's per-frame output when it changes anything."""
    avatar = module.avatar
    body = avatar.body
    if body is None:
        raise SplatrigError("animatable=true: this model has no skinned body (a static scene); export a PLY instead.")
    if "skin_weights" not in avatar.gaussians.params and not module.bake_weights():
        raise SplatrigError(
            f"animatable=true: deformer '{avatar.deformer.registry_name}' has no blend weights to "
            f"bake, so the model cannot be exported as skinned Gaussians; export a PLY instead."
        )
    canonical = avatar.gaussians.gaussians()
    camera = point_camera(module.device)
    transforms, poses, corrected = [], [], {k: [] for k in CORRECTED_FIELDS}
    for i in tqdm(range(motion.num_frames), desc="bone transforms", unit="frame"):
        root = None if motion.roots is None else torch.as_tensor(motion.roots[i])
        batch = frame_batch(camera, torch.as_tensor(motion.poses[i]), root, frames[i])
        T, pose_features = avatar.bone_transforms(batch)  # [J, 4, 4], [3J]
        transforms.append(T.cpu().numpy())
        poses.append(pose_features.reshape(-1, 3).cpu().numpy())
        if corrections:
            out = avatar.corrector(canonical, pose_features)
            for key in CORRECTED_FIELDS:
                corrected[key].append(getattr(out, key).cpu().numpy())
    stored = None
    if corrections:
        stacked = {k: np.stack(v) for k, v in corrected.items()}  # [F, N, ...]
        changed = {k: v != getattr(canonical, k).cpu().numpy()[None] for k, v in stacked.items()}
        if any(c.any() for c in changed.values()):
            sh_changed = np.flatnonzero(changed["sh"].any(axis=(0, 1, 3)))  # coefficient indices
            stacked["sh"] = stacked["sh"][:, :, : int(sh_changed.max()) + 1 if sh_changed.size else 1]
            stored = {f"corrected_{k}": v for k, v in stacked.items()}
    joints = body.rest_joints
    if avatar.pose_refiner is not None and avatar.pose_refiner.enabled:
        joints = joints + avatar.pose_refiner.joint_residual
    return AnimatablePackage(
        canonical=canonical,
        skin_weights=canonical.skin_weights.cpu().numpy(),
        parents=body.parents.cpu().numpy(),
        joint_names=list(body.joint_names),
        rest_joints=joints.detach().cpu().numpy(),
        bone_transforms=np.stack(transforms),
        poses=np.stack(poses),
        fps=float(motion.fps or 25.0),
        stretch=str(avatar.deformer.stretch),
        centres=str(avatar.deformer.centres),
        sh_degree=int(module.sh_degree(module.trained_steps())),
        corrections=stored,
    )
