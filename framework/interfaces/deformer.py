"""Deformers: canonical Gaussians + bone transforms -> posed Gaussians (the paper's LBS step)."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field

from torch import Tensor, nn

from framework.execution import ExecutionMixin
from framework.interfaces.body import BodyModel
from framework.types import Gaussians


@dataclass
class DeformOutput:
    posed: Gaussians  # world-space Gaussians (means, quats, log_scales posed; SH rotated unless sh_frames is set)
    weights: Tensor | None  # [N, J] blend weights used, None for rigid/identity deformers
    aux: dict[str, Tensor] = field(default_factory=dict)  # extra tensors for losses, e.g. "weight_std" [N]
    # [N, 3, 3] rotations when the deformer was asked to defer the SH rotation (`defer_sh`): posed.sh is then still
    # canonical and the colour towards direction d is eval_sh(sh, sh_frames^T d) (framework.splat.sh)
    sh_frames: Tensor | None = None


class Deformer(nn.Module, ExecutionMixin, ABC):
    """Everything the engine asks of a deformer is declared here with a default, so a deformer that implements only
    `forward` trains; one that also implements `bake` gets weight baking, the viewer's and exporter's baked path and
    compaction; one with a part that trains in stage 2 only reads `enabled`."""

    registry_name: str = ""
    #: Whether the part that trains in stage 2 only (the paper's F_dw) is on; the stage switch sets it.
    enabled: bool = True
    #: How skinning treats the blended matrix's stretch (`framework.rig.lbs.STRETCH_MODES`), for exported packages.
    stretch: str = "none"
    #: How Gaussian centres move (`framework.rig.lbs.CENTRE_MODES`), for exported packages.
    centres: str = "blended"

    def bind(self, body: BodyModel | None, bounds: Tensor | None) -> None:  # noqa: B027 - optional hook
        """Called once before training with the body model (or None) and the canonical box [2, 3]."""

    def use_aux(self, keys: frozenset[str]) -> None:  # noqa: B027 - optional hook
        """The aux outputs the losses will read; a deformer may skip computing any other (e.g. L_w's weight std)."""

    def bake(self, gaussians: Gaussians) -> Tensor | None:
        """[N, J] the blend weights this deformer uses for each Gaussian, to store as `skin_weights` so inference
        skips computing them (then `forward` must use `gaussians.skin_weights` when set); None: nothing to bake."""
        return None

    def release_after_bake(self) -> str | None:
        """After `bake`: drop what only computed the now-stored weights (F_dw) and return the registry name of the
        deformer a compact checkpoint loads with (`lbs` for `lbs_residual`); None keeps this one as it is."""
        return None

    def rebuilds_weights(self, means: Tensor, weights: Tensor) -> bool:
        """Whether this deformer, bound afresh, derives exactly `weights` [N, J] at `means` [N, 3] from the body
        alone, so a compact checkpoint may leave them out; False keeps them stored."""
        return False

    @abstractmethod
    def forward(self, gaussians: Gaussians, bone_transforms: Tensor | None, defer_sh: bool = False) -> DeformOutput:
        """bone_transforms: [J, 4, 4] rest-to-posed skinning transforms (None for static scenes).

        defer_sh: the caller can evaluate colours in per-Gaussian frames (one camera), so a rotating deformer may
        return the rotations as `sh_frames` instead of rotating the coefficients; ignoring it is always correct."""
