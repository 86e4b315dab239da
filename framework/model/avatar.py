"""Composes canonical Gaussians -> corrector -> deformer -> rasterizer, the one forward pass every experiment runs.

Static scenes use the same path with no body, the `none` corrector and the `identity` deformer, so `static_fit` and
`paper_full` share every line of training code. The avatar is built with the model's execution (`framework.execution`)
and hands it to every part it holds, so how each runs (torch, or the compiled CPU kernels) is one choice.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from framework.execution import COMPILED, Execution
from framework.interfaces import BodyModel, Corrector, Deformer, Rasterizer
from framework.splat.sh import view_colour_dc
from framework.types import FrameBatch, Gaussians, RenderOutput

# Per-Gaussian tensors the densifier edits; sh is kept as DC + rest so they can have their own learning rates.
GAUSSIAN_KEYS = ("means", "quats", "log_scales", "opacity_logits", "sh0", "shN", "latents", "skin_weights")


class GaussianParams(nn.Module):
    """Canonical Gaussians as named parameters; a densifier may replace any of them with a resized one."""

    def __init__(self, gaussians: Gaussians) -> None:
        super().__init__()
        tensors = {
            "means": gaussians.means,
            "quats": gaussians.quats,
            "log_scales": gaussians.log_scales,
            "opacity_logits": gaussians.opacity_logits,
            "sh0": gaussians.sh[:, :1],
            "shN": gaussians.sh[:, 1:],
        }
        if gaussians.latents is not None:
            tensors["latents"] = gaussians.latents
        if gaussians.skin_weights is not None:
            tensors["skin_weights"] = gaussians.skin_weights
        self.params = nn.ParameterDict(
            {
                k: nn.Parameter(v.detach().clone().float().contiguous(), requires_grad=k != "skin_weights")
                for k, v in tensors.items()
            }
        )

    @property
    def num(self) -> int:
        return int(self.params["means"].shape[0])

    def gaussians(self, sh_degree: int | None = None) -> Gaussians:
        """The canonical Gaussians; with `sh_degree`, only the (sh_degree + 1)^2 coefficients that degree renders."""
        p = self.params
        # Always through cat, even for degree 0: shN then gets a zero gradient rather than none, so Adam's step count
        # and moments evolve exactly as when every band is posed.
        rest = p["shN"] if sh_degree is None else p["shN"][:, : (sh_degree + 1) ** 2 - 1]
        return Gaussians(
            means=p["means"],
            quats=p["quats"],
            log_scales=p["log_scales"],
            opacity_logits=p["opacity_logits"],
            sh=torch.cat([p["sh0"], rest], dim=1),
            latents=p["latents"] if "latents" in p else None,
            skin_weights=p["skin_weights"] if "skin_weights" in p else None,
        )

    def resize_to(self, state_dict: dict[str, Tensor], prefix: str) -> None:
        """Give every parameter the shape stored in a checkpoint before it is loaded (densification changes N); a
        tensor the checkpoint does not hold (latent codes of a compact model whose corrector was folded) is dropped."""
        stored_keys = {k[len(f"{prefix}params.") :] for k in state_dict if k.startswith(f"{prefix}params.")}
        for key in [k for k in self.params if stored_keys and k not in stored_keys]:
            del self.params[key]
        for key, param in self.params.items():
            stored = state_dict.get(f"{prefix}params.{key}")
            if stored is not None and stored.shape != param.shape:
                param.data = torch.zeros(stored.shape, dtype=param.dtype, device=param.device)
        for key, stored in state_dict.items():
            if key.startswith(f"{prefix}params."):
                name = key[len(f"{prefix}params.") :]
                if name not in self.params:
                    self.params[name] = nn.Parameter(torch.zeros_like(stored), requires_grad=name != "skin_weights")


class PoseRefiner(nn.Module):
    """Learnable per-frame residuals on joint rotations and one shared residual on rest joint positions.

    Joint positions are shared across frames: a person's bone lengths do not change between frames, and a
    per-frame offset could explain away appearance instead of fixing calibration of the skeleton.
    """

    def __init__(self, num_frames: int, num_joints: int, enabled: bool = True) -> None:
        super().__init__()
        self.enabled = enabled
        self.pose_residual = nn.Parameter(torch.zeros(num_frames, num_joints, 3))  # [F, J, 3]
        self.joint_residual = nn.Parameter(torch.zeros(num_joints, 3))  # [J, 3]

    def forward(self, frame: Tensor, pose: Tensor, rest_joints: Tensor) -> tuple[Tensor, Tensor]:
        """frame [B], pose [B, J, 3] -> refined pose [B, J, 3], joints [B, J, 3].

        A negative frame id marks a pose from outside the training sequence (a motion file, a hand-made pose): it
        gets the shared joint residual but no per-frame pose residual."""
        joints = rest_joints.expand(pose.shape[0], -1, -1)
        if not self.enabled:
            return pose, joints
        known = (frame >= 0).to(pose.dtype)[:, None, None]  # [B, 1, 1]
        return pose + known * self.pose_residual[frame.clamp_min(0)], joints + self.joint_residual


@dataclass
class AvatarOutput:
    render: RenderOutput
    aux: dict[str, Tensor]
    canonical: Gaussians  # uncorrected canonical Gaussians (what densification looks at)
    posed: Gaussians  # SH still canonical when `forward` deferred its rotation (one camera); see Avatar.pose


class Avatar(nn.Module):
    """The whole model. One camera batch of one frame per call (the paper trains on one image per step)."""

    def __init__(
        self,
        gaussians: GaussianParams,
        rasterizer: Rasterizer,
        corrector: Corrector,
        deformer: Deformer,
        body: BodyModel | None = None,
        pose_refiner: PoseRefiner | None = None,
        background: tuple[float, float, float] = (0.0, 0.0, 0.0),
        execution: Execution = COMPILED,
    ) -> None:
        super().__init__()
        self.execution = execution
        for part in (corrector, deformer, body):
            if part is not None:
                part.set_execution(execution)
        self.gaussians = gaussians
        self.corrector = corrector
        self.deformer = deformer
        self.rasterizer = rasterizer  # the setter hands it the execution
        self.body = body
        self.pose_refiner = pose_refiner
        self.register_buffer("background", torch.tensor(background, dtype=torch.float32), persistent=False)
        # Real-time path: novel views of one pose reuse the corrected, posed Gaussians (inference only).
        self._posed_cache: tuple[bytes, Gaussians, dict[str, Tensor], Tensor | None] | None = None

    @property
    def rasterizer(self) -> Rasterizer:
        return self._rasterizer

    @rasterizer.setter
    def rasterizer(self, backend: Rasterizer) -> None:
        """Swap the backend (viewer, benchmarks, `framework.evaluation.run_cost.use_rasterizer`); it runs with the
        avatar's execution. No other part changes: how they run was chosen with the execution."""
        backend.set_execution(self.execution)
        self._rasterizer = backend

    def _pose_key(self, batch: FrameBatch) -> bytes:
        parts = [batch.frame[:1]]
        parts += [t[:1] for t in (batch.pose, batch.root) if t is not None]
        return b"".join(p.detach().cpu().numpy().tobytes() for p in parts)

    def bone_transforms(self, batch: FrameBatch) -> tuple[Tensor | None, Tensor | None]:
        """World-space skinning transforms [J, 4, 4] and the pose features [P] for the corrector."""
        if self.body is None or batch.pose is None:
            return None, None
        pose = self.body.input_pose(batch.pose[:1])
        joints = self.body.rest_joints.unsqueeze(0)
        if self.pose_refiner is not None:
            pose, joints = self.pose_refiner(batch.frame[:1], pose, self.body.rest_joints.unsqueeze(0))
        transforms = self.body.bone_transforms(pose, joints)[0]  # [J, 4, 4]
        if batch.root is not None:
            transforms = batch.root[0] @ transforms
        return transforms, self.body.pose_features(pose)[0]

    def pose(self, batch: FrameBatch, sh_degree: int | None = None) -> tuple[Gaussians, Gaussians, dict[str, Tensor]]:
        """(canonical, posed, aux): F_a correction then skinning, SH rotated; cached across cameras without gradients.

        With `sh_degree`, the Gaussians carry only the SH coefficients that degree renders, so the corrector and the
        deformer's SH rotation skip the bands the schedule has not switched on yet (they would get zero gradients).
        """
        canonical, posed, aux, _ = self._pose(batch, sh_degree, defer_sh=False)
        return canonical, posed, aux

    def _pose(
        self, batch: FrameBatch, sh_degree: int | None, defer_sh: bool
    ) -> tuple[Gaussians, Gaussians, dict[str, Tensor], Tensor | None]:
        """`pose` plus the deformer's `sh_frames` [N, 3, 3] when `defer_sh` let it leave the SH canonical."""
        canonical = self.gaussians.gaussians(sh_degree)
        key = None
        if not torch.is_grad_enabled() and not self.training:
            key = self._pose_key(batch) + str(sh_degree).encode() + bytes([defer_sh])
            if self._posed_cache is not None and self._posed_cache[0] == key:
                return canonical, *self._posed_cache[1:]
        transforms, pose_features = self.bone_transforms(batch)
        corrected = canonical
        if pose_features is not None:
            corrected = self.corrector(canonical, pose_features)
        deformed = self.deformer(corrected, transforms, defer_sh=defer_sh)
        if key is not None:
            self._posed_cache = (key, deformed.posed, deformed.aux, deformed.sh_frames)
        return canonical, deformed.posed, deformed.aux, deformed.sh_frames

    def train(self, mode: bool = True) -> Avatar:
        self._posed_cache = None
        return super().train(mode)

    def forward(self, batch: FrameBatch, sh_degree: int) -> AvatarOutput:
        """Render the batch's cameras. For one camera the SH rotation is deferred: the colour is evaluated at
        R^T d per Gaussian and handed to the rasterizer as a degree-0 coefficient (the same colour, cheaper than
        rotating every SH band); `posed` in the output then still has canonical SH."""
        canonical, posed, aux, frames = self._pose(batch, sh_degree, defer_sh=batch.cameras.num == 1)
        sh, degree = posed.sh, sh_degree
        if frames is not None:
            sh, degree = self._view_colour(posed, frames, batch, sh_degree), 0
        render = self.rasterizer.render(
            posed.means,
            posed.quats,
            torch.exp(posed.log_scales),
            torch.sigmoid(posed.opacity_logits),
            sh,
            batch.cameras,
            sh_degree=degree,
            background=self.background,
        )
        return AvatarOutput(render=render, aux=aux, canonical=canonical, posed=posed)

    def _view_colour(self, posed: Gaussians, frames: Tensor, batch: FrameBatch, sh_degree: int) -> Tensor:
        """[N, 1, 3] DC coefficients holding each Gaussian's colour towards the one camera (framework.splat.sh);
        compiled (`framework.kernels.sh_colours`, with its backward in training) where the execution compiles them."""
        centre = batch.cameras.centers().to(posed.means)  # [1, 3]
        dirs = posed.means - centre  # [N, 3]
        if self.execution.compiled(posed.sh, dirs, frames):
            from framework.kernels.sh_colours import view_colour_dc_compiled  # imports numba: first use only

            return view_colour_dc_compiled(sh_degree, posed.sh, dirs, frames)
        return view_colour_dc(sh_degree, posed.sh, dirs, frames, self.execution)
