"""Fold a pose corrector whose output hardly changes over the training poses into the canonical Gaussians.

Why: in a near-static capture F_a still helps training (it adds per-Gaussian capacity driven by the latent code;
switching it off measured 1.5 dB worse on the studio's near-static scene at 600 steps), but what it learned is
then almost one constant correction. Evaluated once at every training pose and averaged, that correction can be
written into the Gaussians (opacity, scales, rotation, SH), the corrector and the latent codes dropped, and a novel
pose skips the MLP. The fold is exact for the poses where the correction equals its mean; how far it is from exact
is measured first, as the spread of the corrected attributes over the training poses, in render units:

- colour: RMS over Gaussians of the change of the DC colour (SH_C0 * dSH0), 0..1 colour units;
- opacity: RMS change of sigmoid(logit);
- scale: RMS change of log(scale) (relative size);
- rotation: RMS angle between the corrected rotation and the folded one, in radians.

The fold happens only when the largest of them, over every training pose, is at most `tolerance`.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import torch
from torch import Tensor

from framework.geometry import quat_normalize
from framework.model.avatar import Avatar
from framework.splat.sh import SH_C0
from framework.types import Gaussians

DEFAULT_FOLD_TOLERANCE = 0.01


@dataclass
class CorrectorFold:
    spread: dict[str, float]  # largest RMS deviation per attribute over the training poses (units above)
    tolerance: float
    folded: bool

    @property
    def worst(self) -> float:
        return max(self.spread.values(), default=0.0)


def _attributes(g: Gaussians) -> dict[str, Tensor]:
    return {
        "opacity": g.opacity_logits,
        "log_scales": g.log_scales,
        "quats": quat_normalize(g.quats),
        "sh": g.sh,
    }


def _spread(a: dict[str, Tensor], b: dict[str, Tensor]) -> dict[str, float]:
    """RMS deviations of corrected attributes `a` from `b`, in render units (module docstring)."""
    rms = lambda x: float(x.square().mean().sqrt()) if x.numel() else 0.0  # noqa: E731
    # rotation angle between unit quaternions from their chord (acos of the dot product loses ~3e-4 rad in float32)
    sign = torch.where((a["quats"] * b["quats"]).sum(-1, keepdim=True) < 0, -1.0, 1.0)
    chord = (a["quats"] - sign * b["quats"]).norm(dim=-1)
    return {
        "colour": rms(SH_C0 * (a["sh"][:, 0] - b["sh"][:, 0])),
        "opacity": rms(torch.sigmoid(a["opacity"]) - torch.sigmoid(b["opacity"])),
        "scale": rms(a["log_scales"] - b["log_scales"]),
        "rotation": rms(4.0 * torch.asin((0.5 * chord).clamp(max=1.0))),
    }


@torch.no_grad()
def fold_corrector(avatar: Avatar, pose_features: Iterable[Tensor], tolerance: float = DEFAULT_FOLD_TOLERANCE
                   ) -> CorrectorFold:  # fmt: skip
    """Measure the corrector's spread over `pose_features` (one [P] vector per training pose) and, when it is at
    most `tolerance`, write the mean corrected Gaussians into the avatar's parameters, replace the corrector by
    `none` and drop the latent codes. The caller updates the stored config (`corrector=none`)."""
    canonical = avatar.gaussians.gaussians()
    corrected = [_attributes(avatar.corrector(canonical, pf)) for pf in pose_features]
    if not corrected:
        return CorrectorFold({}, tolerance, False)
    mean = {k: torch.stack([c[k] for c in corrected]).mean(0) for k in corrected[0]}
    mean["quats"] = quat_normalize(mean["quats"])  # corrections are small rotations: the chordal mean is fine
    spread: dict[str, float] = {}
    for c in corrected:
        for k, v in _spread(c, mean).items():
            spread[k] = max(spread.get(k, 0.0), v)
    fold = CorrectorFold(spread, float(tolerance), False)
    if fold.worst > tolerance:
        return fold
    from framework.plugins import load_plugins
    from framework.registry import CORRECTORS

    load_plugins()
    p = avatar.gaussians.params
    p["opacity_logits"].data.copy_(mean["opacity"])
    p["log_scales"].data.copy_(mean["log_scales"])
    p["quats"].data.copy_(mean["quats"])
    p["sh0"].data.copy_(mean["sh"][:, :1])
    p["shN"].data.copy_(mean["sh"][:, 1:])
    if "latents" in p:
        del p["latents"]
    avatar.corrector = CORRECTORS.build("none")
    avatar._posed_cache = None
    fold.folded = True
    return fold
