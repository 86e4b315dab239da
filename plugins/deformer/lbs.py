"""`lbs`: linear blend skinning with weights from the body surface (grid field), as the paper's first stage."""

from __future__ import annotations

from framework.model.lbs_deformer import LBSDeformerBase
from framework.registry import register


@register("deformer", "lbs")
class LBSDeformer(LBSDeformerBase):
    """Plain LBS: grid weights from the body surface (or baked per-Gaussian weights); see `framework.rig.lbs`."""
