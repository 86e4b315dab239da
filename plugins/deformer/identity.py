"""The identity deformer: static scenes live in world space already."""

from __future__ import annotations

from torch import Tensor

from framework.interfaces.deformer import Deformer, DeformOutput
from framework.registry import register
from framework.types import Gaussians


@register("deformer", "identity")
class IdentityDeformer(Deformer):
    """Returns the Gaussians unchanged (no weights, no aux); bone transforms, if any, are ignored."""

    def forward(
        self, gaussians: Gaussians, bone_transforms: Tensor | None = None, defer_sh: bool = False
    ) -> DeformOutput:
        return DeformOutput(posed=gaussians, weights=None, aux={})
