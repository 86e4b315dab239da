"""Learned pruning of a trained avatar: Gaussians that never show, SH bands that carry no colour.

Why after training: densification grows Gaussians wherever a gradient asked for them, and opacity-based pruning during
training only sees opacity, not visibility. What a Gaussian really adds to an image is its blending weight T * alpha;
one whose largest weight over every training view and pose stays below a threshold (default 1/255, one level of an
8-bit image even on a white background) can go. The weights come from the rasterizer's `blend_weights`, a pass
outside the training step (`torch_ref` has one; other backends fall back to it).

Beyond the threshold, `prune_within_tolerance` removes Gaussians in the order of a score while the training frames
still render within a tolerance of the unpruned model (`framework.compaction.render_check`): densification leaves many
small, faint Gaussians whose sum matters little, and the images, not a fixed weight, decide how many. The score
compaction uses is the mean squared blending weight over the pixels a Gaussian covers (`BlendWeights.mean_square`):
removing it changes each of those pixels by about its weight times a colour difference, so the sum of squares is the
image change and the pair count is what it costs every frame to draw. Ranked by that ratio, a large, faint Gaussian
(hundreds of pairs, a little colour each) goes before a small one that is the only thing covering its few pixels;
ranked by the largest weight alone, the other way round. At the same tolerance the ratio keeps fewer Gaussians
(`docs/results/scene_adaptive.md`).

SH bands: band l of a Gaussian changes its colour by an amount whose root mean square over all view directions is
sqrt(sum_m c_lm^2 / 4 pi) per channel (real SH are orthonormal on the sphere). Bands are dropped from the top while
that RMS, averaged over Gaussians, stays below a tolerance in colour units (default 1/255).
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import torch
from torch import Tensor

from framework.compaction.render_check import RenderCheck, largest_passing
from framework.guards import HIDDEN_OPACITY_LOGIT
from framework.interfaces.corrector import Corrector
from framework.interfaces.rasterizer import Rasterizer
from framework.model.avatar import Avatar, GaussianParams
from framework.model.optim_surgery import keep_rows, update_params
from framework.splat.sh import sh_degree_of_bases
from framework.types import BlendWeights, FrameBatch

DEFAULT_MIN_WEIGHT = 1.0 / 255.0
DEFAULT_SH_TOLERANCE = 1.0 / 255.0


def contribution_rasterizer(avatar: Avatar) -> Rasterizer:
    """The avatar's own rasterizer when it reports blending weights, else `torch_ref`."""
    if type(avatar.rasterizer).blend_weights is not Rasterizer.blend_weights:
        return avatar.rasterizer
    from framework.plugins import load_plugins
    from framework.registry import RASTERIZERS

    load_plugins()
    reference = RASTERIZERS.build("torch_ref")
    reference.set_execution(avatar.execution)
    return reference


@torch.no_grad()
def contributions(avatar: Avatar, batches: Iterable[FrameBatch], rasterizer: Rasterizer | None = None) -> BlendWeights:
    """Each canonical Gaussian's blending weights over every (pose, camera) of `batches` (`BlendWeights`: largest,
    sum of squares, pairs), computed with the pose-corrected, posed Gaussians the avatar renders."""
    raster = rasterizer or contribution_rasterizer(avatar)
    was_training = avatar.training
    avatar.eval()
    total = BlendWeights.zeros(avatar.gaussians.num, avatar.gaussians.params["means"].device)
    for batch in batches:
        _, posed, _ = avatar.pose(batch)
        total = total.add(
            raster.blend_weights(
                posed.means,
                posed.quats,
                torch.exp(posed.log_scales),
                torch.sigmoid(posed.opacity_logits),
                batch.cameras,
            )
        )
    avatar.train(was_training)
    return total


def prune_gaussians(params: GaussianParams, keep: Tensor, corrector: Corrector | None = None) -> int:
    """Keep the Gaussians selected by the bool mask `keep` [N]; returns how many were removed. A partially folded
    `corrector`'s rows (`MLPCorrector.active_rows`) are renumbered to the kept Gaussians."""
    before = params.num
    keep_rows(params.params, None, keep)
    rows = None if corrector is None else corrector.corrected_rows()
    if rows is not None and rows.numel():
        new_index = torch.cumsum(keep.long(), 0) - 1  # [N] row of each kept Gaussian after the removal
        corrector.set_corrected_rows(new_index[rows[keep[rows]]])
        if not corrector.corrected_rows().numel():  # every corrected Gaussian went: nothing is pose-dependent any more
            raise ValueError("pruning removed every Gaussian the partially folded corrector corrects; fold it whole.")
    return before - params.num


@torch.no_grad()
def prune_within_tolerance(
    avatar: Avatar, check: RenderCheck, scores: Tensor, tolerance: float, max_fraction: float = 0.9, steps: int = 64
) -> int:
    """Remove the Gaussians with the smallest `scores` [N] (compaction: `BlendWeights.mean_square`; the largest
    blending weight works too), as many as keep `check`'s frames within `tolerance` RMS colour of its reference, at
    most `max_fraction` of them. Bisection over the count (to N / `steps`); a trial hides Gaussians
    (`HIDDEN_OPACITY_LOGIT`), which renders as their removal. Returns how many were removed."""
    n = avatar.gaussians.num
    order = torch.argsort(scores)  # [N] least needed first
    logits = avatar.gaussians.params["opacity_logits"]
    kept = logits.detach().clone()

    def hide_first(k: int) -> bool:
        logits.data.copy_(kept)
        logits.data[order[:k]] = HIDDEN_OPACITY_LOGIT
        return check.rms(avatar) <= tolerance

    k = largest_passing(int(max_fraction * n), hide_first, resolution=max(1, n // steps))
    logits.data.copy_(kept)
    avatar._posed_cache = None
    keep = torch.ones(n, dtype=torch.bool, device=logits.device)
    keep[order[:k]] = False
    return prune_gaussians(avatar.gaussians, keep, avatar.corrector)


def sh_band_rms(shN: Tensor) -> list[float]:
    """RMS colour change over view directions of each band l >= 1, averaged over Gaussians and channels.

    shN [N, K - 1, 3]: the coefficients after the DC term (band l holds rows l^2 - 1 .. (l + 1)^2 - 2)."""
    out = []
    degree = sh_degree_of_bases(shN.shape[1] + 1)
    for band in range(1, degree + 1):
        rows = shN[:, band * band - 1 : (band + 1) ** 2 - 1]  # [N, 2l + 1, 3]
        per_gaussian = (rows.detach().double() ** 2).sum(1) / (4 * math.pi)  # [N, 3] mean square over the sphere
        out.append(float(per_gaussian.sqrt().mean()) if rows.shape[0] else 0.0)
    return out


def negligible_sh_degree(shN: Tensor, tolerance: float = DEFAULT_SH_TOLERANCE, floor: int = 0) -> int:
    """The lowest degree (>= floor) such that every band above it has an RMS colour change below `tolerance`."""
    rms = sh_band_rms(shN)
    degree = len(rms)
    while degree > floor and rms[degree - 1] < tolerance:
        degree -= 1
    return degree


def drop_sh_bands(params: GaussianParams, degree: int) -> None:
    """Keep SH coefficients up to `degree` (shN keeps (degree + 1)^2 - 1 rows)."""
    keep = (degree + 1) ** 2 - 1
    update_params(params.params, None, lambda _n, p: p[:, :keep], lambda _k, v: v[:, :keep], names=["shN"])
