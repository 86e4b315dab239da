"""Compaction steps measured on the images: the training frames rendered before any change, and the RMS colour
difference of a changed avatar's renders from them over the pixels the avatar covers.

Why one reference for every step: pruning, folding F_a and the budgeted versions of both each change the renders a
little; measured against the *original* renders (not the previous step's), a step's tolerance bounds the whole
compaction so far, so the steps cannot add up to more than the last tolerance checked.

Why over the covered pixels: over whole images the background would dilute the difference by the body's share of the
frame (~7 % in the studio), and a tolerance of 1/255 (one level of an 8-bit image) would mean 15 levels on the body.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch

from framework.model.avatar import Avatar
from framework.types import FrameBatch, RenderOutput


def covered_rms(before: Sequence[RenderOutput], after: Sequence[RenderOutput]) -> float:
    """RMS colour difference over the pixels the avatar covers (alpha >= 1/255 in either render)."""
    diffs = []
    for a, b in zip(after, before, strict=True):
        covered = (torch.maximum(a.alpha, b.alpha) >= 1.0 / 255.0).squeeze(-1)  # [C, H, W]
        diffs.append((a.rgb - b.rgb)[covered].reshape(-1))  # [3 * covered pixels]
    d = torch.cat(diffs)
    return float(d.square().mean().sqrt()) if d.numel() else 0.0


@dataclass
class RenderCheck:
    """The frames `batches` as the avatar rendered them when the check was made (`reference`)."""

    batches: Sequence[FrameBatch]
    sh_degree: int
    reference: list[RenderOutput]

    @classmethod
    @torch.no_grad()
    def of(cls, avatar: Avatar, batches: Sequence[FrameBatch], sh_degree: int) -> RenderCheck:
        return cls(batches, sh_degree, [avatar(b, sh_degree=sh_degree).render for b in batches])

    @torch.no_grad()
    def rms(self, avatar: Avatar) -> float:
        """RMS colour difference of `avatar`'s renders from the reference, over the covered pixels."""
        avatar._posed_cache = None  # the caller changed the Gaussians or the corrector in place
        return covered_rms(self.reference, [avatar(b, sh_degree=self.sh_degree).render for b in self.batches])


def largest_passing(n: int, passes: Callable[[int], bool], resolution: int = 1) -> int:
    """The largest k in [0, n] with passes(k), by bisection; passes(0) is taken as true and passes is assumed
    monotone (more removed or folded, more changed). `resolution`: stop when the bracket is this narrow (each test
    renders every checked frame, so a coarse answer is cheaper)."""
    if n <= 0:
        return 0
    if passes(n):
        return n
    lo, hi = 0, n  # passes(lo), not passes(hi)
    while hi - lo > max(1, resolution):
        mid = (lo + hi) // 2
        if passes(mid):
            lo = mid
        else:
            hi = mid
    return lo
