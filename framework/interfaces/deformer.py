"""Deformers: canonical Gaussians + bone transforms -> posed Gaussians (the paper's LBS step)."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field

from torch import Tensor, nn

from framework.types import Gaussians


@dataclass
class DeformOutput:
    posed: Gaussians  # world-space Gaussians (means, quats, log_scales posed; SH rotated unless sh_frames is set)
    weights: Tensor | None  # [N, J] blend weights used, None for rigid/identity deformers
    aux: dict[str, Tensor] = field(default_factory=dict)  # extra tensors for losses, e.g. "weight_std" [N]
    # [N, 3, 3] rotations when the deformer was asked to defer the SH rotation (`defer_sh`): posed.sh is then still
    # canonical and the colour towards direction d is eval_sh(sh, sh_frames^T d) (framework.splat.sh)
    sh_frames: Tensor | None = None


class Deformer(nn.Module, ABC):
    registry_name: str = ""

    def bind(self, body: object | None, bounds: Tensor | None) -> None:  # noqa: B027 - optional hook
        """Called once before training with the body model (or None) and the canonical box [2, 3]."""

    def use_aux(self, keys: frozenset[str]) -> None:  # noqa: B027 - optional hook
        """The aux outputs the losses will read; a deformer may skip computing any other (e.g. L_w's weight std)."""

    @abstractmethod
    def forward(self, gaussians: Gaussians, bone_transforms: Tensor | None, defer_sh: bool = False) -> DeformOutput:
        """bone_transforms: [J, 4, 4] rest-to-posed skinning transforms (None for static scenes).

        defer_sh: the caller can evaluate colours in per-Gaussian frames (one camera), so a rotating deformer may
        return the rotations as `sh_frames` instead of rotating the coefficients; ignoring it is always correct."""
