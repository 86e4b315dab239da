"""Fold a pose corrector whose output hardly changes over the training poses into the canonical Gaussians.

Why: in a near-static capture F_a still helps training (it adds per-Gaussian capacity driven by the latent code;
switching it off measured 1.5 dB worse on the studio's near-static scene at 600 steps), but what it learned is
then almost one constant correction. Evaluated at every training pose and averaged, that correction can be written
into the Gaussians (opacity, scales, rotation, SH), the corrector and the latent codes dropped, and a novel pose
skips the MLP. The fold is exact where the correction equals its mean; whether it is close enough is decided on what
matters, the images: the training frames are rendered before and after, and the fold is kept only when the RMS
colour difference over the pixels the avatar covers is at most `tolerance` (default 1/255, one level of an 8-bit
image). The spread of the corrected attributes over the poses is reported too (RMS over Gaussians, the largest over
poses; colour in 0..1 units, opacity after the sigmoid, log-scale, rotation angle in radians) to show which attribute
the corrector still moves; it is not the criterion, because invisible Gaussians can change a lot without changing an
image.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from framework.geometry import quat_normalize
from framework.model.avatar import Avatar
from framework.splat.sh import SH_C0
from framework.types import FrameBatch, Gaussians, RenderOutput

DEFAULT_FOLD_TOLERANCE = 1.0 / 255.0


@dataclass
class CorrectorFold:
    spread: dict[str, float]  # largest RMS deviation per attribute over the training poses (units above)
    render_rms: float  # RMS colour difference of the training frames' renders where the avatar is, folded vs not
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


def _covered_rms(before: Sequence[RenderOutput], after: Sequence[RenderOutput]) -> float:
    """RMS colour difference over the pixels the avatar covers (alpha >= 1/255 in either render): over whole images
    the background would dilute it by the body's share of the frame (~7 % in the studio)."""
    diffs = []
    for a, b in zip(after, before, strict=True):
        covered = (torch.maximum(a.alpha, b.alpha) >= 1.0 / 255.0).squeeze(-1)  # [C, H, W]
        diffs.append((a.rgb - b.rgb)[covered].reshape(-1))  # [3 * covered pixels]
    d = torch.cat(diffs)
    return float(d.square().mean().sqrt()) if d.numel() else 0.0


@torch.no_grad()
def fold_corrector(avatar: Avatar, batches: Sequence[FrameBatch], sh_degree: int,
                   tolerance: float = DEFAULT_FOLD_TOLERANCE) -> CorrectorFold:  # fmt: skip
    """Fold the corrector into the Gaussians when the training frames `batches` render within `tolerance` (RMS
    colour) of the unfolded avatar: the mean corrected Gaussians replace the canonical ones, the corrector becomes
    `none` and the latent codes go. Otherwise the avatar is left exactly as it was. The caller updates the stored
    config (`corrector=none`)."""
    if not batches:
        return CorrectorFold({}, 0.0, tolerance, False)
    canonical = avatar.gaussians.gaussians()
    corrected = [_attributes(avatar.corrector(canonical, avatar.bone_transforms(b)[1])) for b in batches]
    mean = {k: torch.stack([c[k] for c in corrected]).mean(0) for k in corrected[0]}
    mean["quats"] = quat_normalize(mean["quats"])  # corrections are small rotations: the chordal mean is fine
    spread: dict[str, float] = {}
    for c in corrected:
        for k, v in _spread(c, mean).items():
            spread[k] = max(spread.get(k, 0.0), v)
    before = [avatar(b, sh_degree=sh_degree).render for b in batches]

    from framework.plugins import load_plugins
    from framework.registry import CORRECTORS

    load_plugins()
    p = avatar.gaussians.params
    keys = ("opacity_logits", "log_scales", "quats", "sh0", "shN")
    kept = {k: p[k].detach().clone() for k in keys}
    corrector, latents = avatar.corrector, p["latents"] if "latents" in p else None
    p["opacity_logits"].data.copy_(mean["opacity"])
    p["log_scales"].data.copy_(mean["log_scales"])
    p["quats"].data.copy_(mean["quats"])
    p["sh0"].data.copy_(mean["sh"][:, :1])
    p["shN"].data.copy_(mean["sh"][:, 1:])
    avatar.corrector = CORRECTORS.build("none")
    avatar._posed_cache = None
    after = [avatar(b, sh_degree=sh_degree).render for b in batches]
    rms = _covered_rms(before, after)
    fold = CorrectorFold(spread, rms, float(tolerance), rms <= tolerance)
    if fold.folded:
        if latents is not None:
            del p["latents"]
        return fold
    for k in keys:  # not close enough: put everything back
        p[k].data.copy_(kept[k])
    avatar.corrector = corrector
    avatar._posed_cache = None
    return fold
