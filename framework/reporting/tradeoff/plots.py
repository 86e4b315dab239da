"""The trade-off's plots: novel-pose PSNR against one objective per figure, with seed error bars and that plane's
front marked. matplotlib is imported inside, so the rest of the report loads without it."""

from __future__ import annotations

import math

from framework.reporting.tradeoff.points import Objective, Point, points_split, psnr_label


def _err(values: list[float]) -> list[float]:
    """Error-bar half widths: a std over seeds, none drawn (0) where one seed left it unknown."""
    return [0.0 if math.isnan(v) else v for v in values]


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def figure(points: list[Point], objective: Objective):
    """Novel-pose PSNR against one objective (see `draw`), one figure."""
    fig, ax = _pyplot().subplots(figsize=(5.0, 3.8))
    draw(ax, points, objective)
    fig.tight_layout()
    return fig


def overview(points: list[Point], objectives: tuple[Objective, ...]):
    """The planes side by side in one 2-column figure: the picture a README shows."""
    rows = math.ceil(len(objectives) / 2)
    fig, axes = _pyplot().subplots(rows, 2, figsize=(9.0, 3.4 * rows), sharey=True, squeeze=False)
    for ax, objective in zip(axes.flat, objectives, strict=False):
        draw(ax, points, objective)
    for ax in list(axes.flat)[len(objectives) :]:
        ax.set_visible(False)
    fig.tight_layout()
    return fig


def draw(ax, points: list[Point], objective: Objective) -> None:
    """Novel-pose PSNR against one objective on `ax`, with error bars (std over seeds) on both axes; the front of that
    plane joined by a line, its members filled when they are on every seed's front and hollow when not; every point
    labelled."""
    key = objective.key
    shown = [p for p in points if not math.isnan(p.psnr) and not math.isnan(getattr(p, key))]
    ax.errorbar(
        [getattr(p, key) for p in shown],
        [p.psnr for p in shown],
        xerr=_err([p.std(key) for p in shown]),
        yerr=_err([p.std("psnr") for p in shown]),
        fmt="none",
        ecolor="0.55",
        elinewidth=0.7,
        capsize=1.5,
        zorder=1,
    )
    groups = (
        ("dominated", lambda p: not p.front[key], dict(c="0.6", s=18)),
        ("Pareto front", lambda p: p.front[key] and not p.seed_unstable[key], dict(c="tab:red", s=30)),
        (
            "front member on some seeds only",
            lambda p: p.front[key] and p.seed_unstable[key],
            dict(facecolors="none", edgecolors="tab:red", s=30, linewidths=1.2),
        ),
    )
    for label, keep, style in groups:
        sel = [p for p in shown if keep(p)]
        if sel:
            ax.scatter([getattr(p, key) for p in sel], [p.psnr for p in sel], zorder=3, label=label, **style)
    front = sorted((p for p in shown if p.front[key]), key=lambda p: getattr(p, key))
    ax.plot([getattr(p, key) for p in front], [p.psnr for p in front], c="tab:red", lw=1, zorder=2)
    for p in shown:
        ax.annotate(p.label, (getattr(p, key), p.psnr), fontsize=6, xytext=(3, 2), textcoords="offset points")
    xs = [getattr(p, key) for p in shown]
    if xs and min(xs) > 0 and max(xs) / min(xs) > 20:
        ax.set_xscale("log")
    better = "right is better" if objective.maximise else "left is better"
    ax.set_xlabel(f"{objective.label} ({better})", fontsize=8)
    split = points_split(points)
    ax.set_ylabel(f"{psnr_label(split)} (dB)", fontsize=8)
    ax.ticklabel_format(axis="y", useOffset=False)
    ax.tick_params(labelsize=7)
    ax.grid(alpha=0.3)
    if shown:
        ax.legend(fontsize=7)
