"""Speed per dB lost: for each single-knob point, how much training and viewer speed it buys against the baseline per
dB of novel-pose PSNR (the points' judged split) it costs, so the knobs worth turning first come first."""

from __future__ import annotations

import math
from dataclasses import dataclass

from framework.reporting.tradeoff.points import BASELINE, Point

PRESET_PREFIX = "preset_"
LOSS_NOISE_DB = 0.01  # a PSNR loss below this counts as none (the metric's own rounding noise)


@dataclass(frozen=True)
class KnobGain:
    label: str
    db_lost: float  # baseline PSNR - point PSNR (negative: the knob gained quality)
    train_speedup: float  # baseline training time / point's
    fps_speedup: float  # point's viewer fps (compiled path) / baseline's
    doublings: float  # log2(train_speedup) + log2(fps_speedup): speed-up of training and rendering together
    per_db: float  # doublings per dB lost; inf when less than LOSS_NOISE_DB is lost


def knob_gains(points: list[Point]) -> list[KnobGain]:
    """Speed gained per dB of novel-pose PSNR lost, for every single-knob point against the baseline, best first:
    points that lose nothing and gain speed first (by their gain), then by doublings per dB lost, then points that
    gain no speed. Empty without a baseline point."""
    base = next((p for p in points if p.label == BASELINE), None)
    if base is None:
        return []
    gains = []
    for p in points:
        if p is base or p.label.startswith(PRESET_PREFIX):
            continue
        train, fps = base.train_min / p.train_min, p.fps / base.fps
        doublings = math.log2(train) + math.log2(fps)
        lost = base.psnr - p.psnr
        per_db = math.inf if lost < LOSS_NOISE_DB else doublings / lost
        gains.append(KnobGain(p.label, lost, train, fps, doublings, per_db))

    def rank(g: KnobGain) -> tuple:
        if math.isnan(g.doublings) or g.doublings <= 0:
            return (2, -g.doublings if not math.isnan(g.doublings) else math.inf, g.label)
        if math.isinf(g.per_db):
            return (0, -g.doublings, g.label)
        return (1, -g.per_db, g.label)

    return sorted(gains, key=rank)
