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

Partial fold: in a walking capture F_a moves some Gaussians (a bending elbow's folds) and hardly touches most others,
so folding all of it fails the check while folding most of it would not. The Gaussians are ranked by how much their
correction varies over the training poses, weighted by how visible they are (largest blending weight), and the
largest prefix of that ranking whose fold keeps the renders within the tolerance is folded (bisection); the MLP then
runs on the remaining rows only (`MLPCorrector.active_rows`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from framework.compaction.pruning import contributions
from framework.compaction.render_check import RenderCheck, largest_passing
from framework.geometry import quat_normalize
from framework.model.avatar import Avatar
from framework.splat.sh import SH_C0
from framework.types import FrameBatch, Gaussians

DEFAULT_FOLD_TOLERANCE = 1.0 / 255.0
PARTIAL_FOLD_STEPS = 64  # the bisection stops at N / 64 Gaussians: ~6 renders of the checked frames
MIN_PARTIAL_FRACTION = 0.05  # a partial fold of fewer Gaussians is not worth the row bookkeeping
_KEYS = ("opacity_logits", "log_scales", "quats", "sh0", "shN")


@dataclass
class CorrectorFold:
    spread: dict[str, float]  # largest RMS deviation per attribute over the training poses (units above)
    render_rms: float  # RMS colour difference of the checked frames' renders from the uncompacted model's
    tolerance: float
    folded: bool  # the whole corrector went (its MLP and the latent codes)
    folded_gaussians: int = 0  # Gaussians whose correction is now in their parameters (all when folded)
    num_gaussians: int = 0

    @property
    def worst(self) -> float:
        return max(self.spread.values(), default=0.0)


def fold_outcome(fold: dict) -> str:
    """What happened to F_a, in words, from a `CorrectorFold` as a dict (as reports store it)."""
    if fold["folded"]:
        return "folded into the Gaussians"
    if fold.get("folded_gaussians"):
        return f"folded for {fold['folded_gaussians']} of {fold['num_gaussians']} Gaussians (the MLP runs on the rest)"
    return "kept"


def _attributes(g: Gaussians) -> dict[str, Tensor]:
    return {
        "opacity": g.opacity_logits,
        "log_scales": g.log_scales,
        "quats": quat_normalize(g.quats),
        "sh": g.sh,
    }


def _deviation(a: dict[str, Tensor], b: dict[str, Tensor]) -> dict[str, Tensor]:
    """Per-Gaussian deviations [N] of corrected attributes `a` from `b`, in render units (module docstring)."""
    # rotation angle between unit quaternions from their chord (acos of the dot product loses ~3e-4 rad in float32)
    sign = torch.where((a["quats"] * b["quats"]).sum(-1, keepdim=True) < 0, -1.0, 1.0)
    chord = (a["quats"] - sign * b["quats"]).norm(dim=-1)
    return {
        "colour": (SH_C0 * (a["sh"][:, 0] - b["sh"][:, 0])).square().mean(-1).sqrt(),
        "opacity": (torch.sigmoid(a["opacity"]) - torch.sigmoid(b["opacity"])).abs(),
        "scale": (a["log_scales"] - b["log_scales"]).square().mean(-1).sqrt(),
        "rotation": 4.0 * torch.asin((0.5 * chord).clamp(max=1.0)),
    }


def _write_mean(p, mean: dict[str, Tensor], kept: dict[str, Tensor], rows: Tensor | None) -> None:
    """Parameters = the kept ones, with the mean correction written into `rows` (None: every row)."""
    new = {
        "opacity_logits": mean["opacity"],
        "log_scales": mean["log_scales"],
        "quats": mean["quats"],
        "sh0": mean["sh"][:, :1],
        "shN": mean["sh"][:, 1:],
    }
    for k in _KEYS:
        value = new[k] if rows is None else kept[k].index_copy(0, rows, new[k].index_select(0, rows))
        p[k].data.copy_(value)


@torch.no_grad()
def fold_corrector(
    avatar: Avatar,
    batches: Sequence[FrameBatch],
    sh_degree: int,
    tolerance: float = DEFAULT_FOLD_TOLERANCE,
    check: RenderCheck | None = None,
    partial: bool = False,
) -> CorrectorFold:
    """Fold the corrector into the Gaussians when the frames render within `tolerance` (RMS colour) of `check`'s
    reference (default: the avatar's own renders of `batches` now): the mean corrected Gaussians replace the canonical
    ones, the corrector becomes `none` and the latent codes go. Otherwise, with `partial`, fold the largest share of
    the Gaussians that stays within the tolerance (the MLP keeps the rest), or leave the avatar exactly as it was.
    The caller updates the stored config (`corrector=none`) when `folded`."""
    n = avatar.gaussians.num
    if not batches:
        return CorrectorFold({}, 0.0, tolerance, False, 0, n)
    check = check or RenderCheck.of(avatar, batches, sh_degree)
    canonical = avatar.gaussians.gaussians()
    corrected = [_attributes(avatar.corrector(canonical, avatar.bone_transforms(b)[1])) for b in batches]
    mean = {k: torch.stack([c[k] for c in corrected]).mean(0) for k in corrected[0]}
    mean["quats"] = quat_normalize(mean["quats"])  # corrections are small rotations: the chordal mean is fine
    spread: dict[str, float] = {}
    variation = torch.zeros(n, device=canonical.means.device)  # [N] the largest deviation over poses, summed
    for c in corrected:
        dev = _deviation(c, mean)
        for k, v in dev.items():
            spread[k] = max(spread.get(k, 0.0), float(v.square().mean().sqrt()) if v.numel() else 0.0)
        variation = torch.maximum(variation, sum(dev.values()))

    from framework.plugins import load_plugins
    from framework.registry import CORRECTORS

    load_plugins()
    p = avatar.gaussians.params
    kept = {k: p[k].detach().clone() for k in _KEYS}
    corrector, latents = avatar.corrector, p["latents"] if "latents" in p else None
    _write_mean(p, mean, kept, None)
    avatar.corrector = CORRECTORS.build("none")
    rms = check.rms(avatar)
    if rms <= tolerance:
        if latents is not None:
            del p["latents"]
        return CorrectorFold(spread, rms, float(tolerance), True, n, n)
    avatar.corrector = corrector  # not close enough: put everything back, then try a part
    _restore(p, kept)
    rows = corrector.corrected_rows()
    if partial and rows is not None and not rows.numel() and n > 1:
        order = torch.argsort(variation * contributions(avatar, batches).max)  # least needed first

        def fold_first(k: int) -> float:  # k < n: an empty active_rows would mean "every row"
            _write_mean(p, mean, kept, order[:k])
            corrector.set_corrected_rows(torch.sort(order[k:]).values)
            return check.rms(avatar)

        step = max(1, n // PARTIAL_FOLD_STEPS)
        k = largest_passing(n - 1, lambda k: fold_first(k) <= tolerance, resolution=step)
        if k >= MIN_PARTIAL_FRACTION * n:
            return CorrectorFold(spread, fold_first(k), float(tolerance), False, k, n)
        _restore(p, kept)
        corrector.set_corrected_rows(rows.new_zeros(0))
    avatar._posed_cache = None
    return CorrectorFold(spread, rms, float(tolerance), False, 0, n)


def _restore(p, kept: dict[str, Tensor]) -> None:
    for k in _KEYS:
        p[k].data.copy_(kept[k])
