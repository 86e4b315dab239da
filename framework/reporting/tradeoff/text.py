"""The trade-off report as text: the Markdown (caption, points table with its front footnote, recommendations by
budget, speed per dB lost) and the two CSVs (points, recommendations)."""

from __future__ import annotations

import math

from framework.plugins import format_table
from framework.reporting.csv_text import csv_text
from framework.reporting.runs import Run
from framework.reporting.stats import Difference
from framework.reporting.tradeoff.budgets import Recommendation
from framework.reporting.tradeoff.gains import KnobGain
from framework.reporting.tradeoff.points import (
    ALL,
    BASELINE,
    PLANES,
    QUANTITIES,
    SIDE_PSNRS,
    STORED_POSES,
    TRUE_POSES,
    Point,
    front_label,
    points_split,
    psnr_flips,
    psnr_label,
    side_psnrs,
)

NONE_MEETS = "none measured meets it"


def _fmt(x: float, digits: int = 2) -> str:
    return "-" if math.isnan(x) else f"{x:.{digits}f}"


def _pm(mean: float, std: float, digits: int = 2, sign: bool = False) -> str:
    """'mean ± std', or the mean alone where the std is unknown (one seed)."""
    if math.isnan(mean):
        return "-"
    text = f"{mean:+.{digits}f}" if sign else f"{mean:.{digits}f}"
    return text if math.isnan(std) else f"{text} ± {std:.{digits}f}"


def _viewer_settings(runs: list[Run]) -> dict[str, list[str]]:
    """The viewer benchmark's settings over the runs that have one: resolution, device, warmup, frames."""
    measured = [r.record["viewer_fps"] for r in runs if r.record.get("viewer_fps")]
    keys = ("resolution", "device", "warmup", "frames")
    return {k: sorted({str(m.get(k)) for m in measured}) for k in keys} | {"runs": [str(len(measured))]}


def _fps_headers(runs: list[Run]) -> tuple[str, str]:
    """Column titles of the two fps columns, naming the resolution when every run measured at the same one."""
    resolutions = _viewer_settings(runs)["resolution"]
    at = f" {resolutions[0]}²" if len(resolutions) == 1 else ""
    return f"fps{at} compiled", f"fps{at} torch_ref"


def psnr_caption(split: str, runs: list[Run]) -> str:
    """Which split the PSNR is judged on, and why where it is the true poses; on the stored poses, how many runs
    hold the true-pose split where some do (all must, for it to be judged on)."""
    if split == TRUE_POSES:
        return (
            f"PSNR: whole image, on the held-out motion rendered with the true poses ({TRUE_POSES}, which every run "
            "holds), the PSNR every point, front, budget and Δ is judged by: the stored poses carry the studio's "
            f"pose-fit noise, which compresses and can flip differences between points (stored-pose PSNR, "
            f"{STORED_POSES}, beside it)."
        )
    text = f"PSNR: whole image, on the held-out motion rendered with its stored poses ({split})."
    having = sum(r.metric(TRUE_POSES, "image", "psnr") is not None for r in runs)
    if split == STORED_POSES and 0 < having < len(runs):
        text += (
            f" {having} of {len(runs)} runs hold {TRUE_POSES}; the report judges on it only when every run does "
            "(tools/record_true_poses.py)."
        )
    return text


def caption(points: list[Point], runs: list[Run]) -> str:
    """How the table was measured: runs, steps, the split the PSNR is on, the viewer benchmark's settings, the seeds
    per point."""
    steps = sorted({int(r.record.get("steps", 0)) for r in runs})
    v = _viewer_settings(runs)
    if v["runs"] == ["0"]:
        fps = "fps: no run has viewer_fps (results.json), so the fps columns are empty."
    else:
        fps = (
            f"fps: novel-pose frames per second of the viewer at {'/'.join(v['resolution'])}² on "
            f"{'/'.join(v['device'])} ({'/'.join(v['warmup'])} warm-up, {'/'.join(v['frames'])} timed frames), from "
            f"viewer_fps in results.json of {v['runs'][0]} of {len(runs)} runs; compiled = numba rasterizer and "
            "compiled CPU kernels (the fps objective), torch_ref = torch_ref rasterizer with torch kernels."
        )
    counts: dict[int, int] = {}
    for p in points:
        counts[len(p.seeds)] = counts.get(len(p.seeds), 0) + 1
    seeds = ", ".join(
        f"{n} seed{'s' if n != 1 else ''} for {c} point{'s' if c != 1 else ''}" for n, c in sorted(counts.items())
    )
    return (
        f"{len(runs)} runs, {len(points)} points; training steps {', '.join(map(str, steps))}; {seeds}. Each number "
        f"is the mean over the point's seeds (PSNR: mean ± sample std). {psnr_caption(points_split(points), runs)} "
        f"{fps}"
    )


def points_markdown(points: list[Point], fps_headers: tuple[str, str]) -> str:
    split = points_split(points)
    side = side_psnrs(split)
    header = (
        "point",
        "seeds",
        "front",
        psnr_label(split),
        *(SIDE_PSNRS[k][1] for k in side),
        *fps_headers,
        "train min",
        "peak MiB",
        "model MB",
        "Gaussians",
    )
    rows = [
        (
            p.label,
            ",".join(map(str, p.seeds)),
            front_label(p),
            _pm(p.psnr, p.std("psnr")),
            *(_pm(p.stats[k].mean, p.std(k)) for k in side),
            _fmt(p.fps, 1),
            _fmt(p.fps_torch, 1),
            _fmt(p.train_min),
            _fmt(p.peak_mib, 0),
            _fmt(p.model_mb, 3),
            _fmt(p.num_gaussians, 0),
        )
        for p in points
    ]
    return format_table(rows, header)


def front_footnote(points: list[Point]) -> str:
    """The one line under the table: what yes* means, and the front neighbours whose PSNR order flips by seed."""
    text = (
        "front: on the Pareto front of all five objectives (higher PSNR and compiled fps, lower training time, memory "
        "and size) over the seed means; yes* = not on every seed's front (each seed's front over the points that have "
        "that seed)."
    )
    flips = {o.key: psnr_flips(points, o.key) for o in PLANES}
    listed = "; ".join(f"{k}: " + ", ".join(f"{a} / {b}" for a, b in pairs) for k, pairs in flips.items() if pairs)
    if listed:
        text += f" Neighbours on a (PSNR, x) front whose PSNR order flips between seeds: {listed}."
    return text


def _delta_text(rec: Recommendation) -> str:
    if rec.delta is None:
        return "-"
    return _pm(rec.delta.delta, rec.delta.sigma, sign=True)


def recommendations_markdown(recs: list[Recommendation], fps_headers: tuple[str, str], split: str | None = None) -> str:
    """One row per budget; `split` names the PSNR column (default: the recommended points' split)."""
    split = points_split([r.point for r in recs if r.point is not None]) if split is None else split
    header = (
        "budget",
        "point",
        "config to paste",
        psnr_label(split),
        "Δ dB vs baseline",
        "train min",
        *fps_headers,
        "seeds",
    )
    rows = []
    for r in recs:
        p = r.point
        if p is None:
            rows.append((f"`{r.budget}`", NONE_MEETS, "", "", "", "", "", "", ""))
            continue
        paste = ", then ".join(f"`{s}`" for s in r.paste)
        rows.append(
            (
                f"`{r.budget}`",
                p.label,
                paste,
                _pm(p.psnr, p.std("psnr")),
                _delta_text(r),
                _fmt(p.train_min),
                _fmt(p.fps, 1),
                _fmt(p.fps_torch, 1),
                ",".join(map(str, p.seeds)),
            )
        )
    return format_table(rows, header)


def gains_markdown(gains: list[KnobGain]) -> str:
    def per_db(g: KnobGain) -> str:
        if math.isnan(g.doublings) or g.doublings <= 0:
            return "no speed gained"
        return "free" if math.isinf(g.per_db) else _fmt(g.per_db)

    rows = [
        (g.label, _fmt(g.db_lost), f"{_fmt(g.train_speedup)}x", f"{_fmt(g.fps_speedup)}x", _fmt(g.doublings), per_db(g))
        for g in gains
    ]
    header = ("knob", "dB lost", "training speed-up", "fps speed-up", "speed doublings", "doublings per dB lost")
    return format_table(rows, header)


def to_markdown(points: list[Point], runs: list[Run], recs: list[Recommendation], gains: list[KnobGain]) -> str:
    fps_headers = _fps_headers(runs)
    split = points_split(points)
    judged = psnr_label(split)
    parts = [
        "# Speed / size / accuracy trade-off",
        "",
        caption(points, runs) + " Front members first, then by PSNR.",
        "",
        points_markdown(points, fps_headers),
        "",
        front_footnote(points),
        "",
        "## Recommendations by budget",
        "",
        f"For each budget, the measured point with the best mean {judged} whose mean meets it (no "
        "interpolation between points). Δ dB vs baseline = mean difference ± sqrt(s_p²/n_p + s_b²/n_b) over seeds; "
        "`<run>` is the folder your training run wrote.",
        "",
        recommendations_markdown(recs, fps_headers, split),
        "",
        "## Speed per dB lost (single knobs against the baseline)",
        "",
    ]
    if gains:
        parts += [
            "Speed doublings = log2(training speed-up) + log2(viewer fps speed-up, compiled path); per dB lost = "
            f'doublings / (baseline PSNR - point PSNR, {judged}); "free" = less than 0.01 dB lost. Best first: the '
            "first three rows are the knobs that buy the most speed per dB.",
            "",
            gains_markdown(gains),
        ]
    elif any(p.label == BASELINE for p in points):
        parts.append(f"(no point besides `{BASELINE}`: no knob to compare with it)")
    else:
        parts.append(f"(no `{BASELINE}` point among the runs: nothing to compare the knobs with)")
    return "\n".join(parts) + "\n"


def to_csv(points: list[Point]) -> str:
    """One row per point; `psnr` is on the split in `psnr_split`, the side PSNRs are those the table shows."""
    split = points_split(points)
    shown = tuple(k for k in QUANTITIES if k not in SIDE_PSNRS or k in side_psnrs(split))
    header = (
        "point",
        "seeds",
        "on_front",
        "front_seed_unstable",
        *shown,
        *(f"{k}_std" for k in shown),
        *(f"front_{o.key}" for o in PLANES),
        *(f"seed_unstable_{o.key}" for o in PLANES),
        "psnr_split",
    )
    rows = (
        (
            p.label,
            " ".join(map(str, p.seeds)),
            int(p.on_front),
            int(p.seed_unstable[ALL]),
            *(p.stats[k].mean for k in shown),
            *(p.std(k) for k in shown),
            *(int(p.front[o.key]) for o in PLANES),
            *(int(p.seed_unstable[o.key]) for o in PLANES),
            p.split,
        )
        for p in points
    )
    return csv_text(header, rows)


RECOMMENDATION_COLUMNS = (
    "budget",
    "point",
    "config",
    "psnr",
    "psnr_std",
    "delta_db",
    "delta_sigma",
    "train_min",
    "fps",
    "fps_torch",
    "seeds",
    "psnr_split",
)


def _recommendation_row(r: Recommendation) -> tuple[object, ...]:
    p = r.point
    if p is None:
        return (str(r.budget), NONE_MEETS, *[""] * (len(RECOMMENDATION_COLUMNS) - 2))
    d = r.delta or Difference(math.nan, math.nan)
    return (
        str(r.budget),
        p.label,
        " ; then ".join(r.paste),
        p.psnr,
        p.std("psnr"),
        d.delta,
        d.sigma,
        p.train_min,
        p.fps,
        p.fps_torch,
        " ".join(map(str, p.seeds)),
        p.split,
    )


def recommendations_csv(recs: list[Recommendation]) -> str:
    return csv_text(RECOMMENDATION_COLUMNS, map(_recommendation_row, recs))
