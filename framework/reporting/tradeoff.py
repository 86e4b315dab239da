"""The speed / size / accuracy trade-off (sweeps/tradeoff.yaml) from the runs' results.json: novel-pose PSNR against
render fps (novel pose), training time, peak memory and model size.

A point is a variant (`framework.reporting.runs`: runs that differ only by seed), labelled by its trade-off config
(`+tradeoff=NAME`) or, for runs outside the trade-off sweep, by its experiment; every number is the mean over its
seeds. Written: one PNG per objective with that plane's Pareto front marked (maximise PSNR and fps, minimise the
others), the same plots in TensorBoard, a Markdown table with the front over all five objectives first, a CSV, the
best point for each budget a user names (`'budgets=["fps>=60"]'`) and the knobs that buy the most speed per dB lost.
"""

from __future__ import annotations

import csv
import io
import math
import operator
import re
from dataclasses import dataclass, field
from pathlib import Path

from framework.atomic import atomic_write_text
from framework.plugins import format_table
from framework.reporting.figures import save_png
from framework.reporting.pareto import pareto_front
from framework.reporting.runs import ReportError, Run, group_runs
from framework.reporting.stats import spread

BASELINE = "baseline"
PRESET_PREFIX = "preset_"
PSNR = ("novel_pose", "image", "psnr")  # the quality every point is judged by
LOSS_NOISE_DB = 0.01  # a PSNR loss below this counts as none (the metric's own rounding noise)


@dataclass(frozen=True)
class Objective:
    key: str  # attribute of Point, and the name a budget uses
    label: str
    maximise: bool
    file: str  # the plot's PNG name


OBJECTIVES = (
    Objective("fps", "render fps, novel pose", True, "tradeoff_fps.png"),
    Objective("train_min", "training time (min)", False, "tradeoff_train_time.png"),
    Objective("peak_mib", "peak training memory (MiB)", False, "tradeoff_memory.png"),
    Objective("model_mb", "model size (MB, learned tensors)", False, "tradeoff_model_size.png"),
)
DEFAULT_BUDGETS = ("fps>=60", "train_min<=5", "model_mb<=10")
BUDGET_KEYS = ("psnr", *(o.key for o in OBJECTIVES))


@dataclass
class Point:
    label: str
    seeds: tuple[int, ...]
    psnr: float  # novel-pose PSNR (whole image, dB)
    fps: float  # novel-pose render fps
    train_min: float  # training wall time (minutes)
    peak_mib: float  # peak memory of the fit loop: CUDA allocated where measured, else resident (RSS)
    model_mb: float  # learned tensors, 10^6 bytes
    num_gaussians: float
    on_front: bool = False  # on the front of all five objectives
    front: dict[str, bool] = field(default_factory=dict)  # objective key -> on the (PSNR, objective) front


def _number(value) -> float:
    return math.nan if value is None else float(value)


def _cost(run: Run) -> dict[str, float]:
    r = run.record
    memory = r.get("cuda_peak_mib")
    return {
        "psnr": _number(run.metric(*PSNR)),
        "fps": _number((r.get("render_fps") or {}).get("novel_pose")),
        "train_min": _number(r.get("train_seconds")) / 60,
        "peak_mib": _number(memory if memory is not None else r.get("peak_rss_mib")),
        "model_mb": _number(r.get("model_bytes")) / 1e6,
        "num_gaussians": _number(r.get("num_gaussians")),
    }


def tradeoff_name(run: Run) -> str:
    """The run's trade-off point (`+tradeoff=NAME` among its overrides), else its experiment."""
    for item in run.variant:
        key, _, value = item.partition("=")
        if key.lstrip("+~") == "tradeoff":
            return value
    return run.experiment


def build_points(runs: list[Run]) -> list[Point]:
    """One point per variant, means over seeds, with every front computed."""
    groups = group_runs(runs)
    variants = list(groups)
    shared = set(variants[0]).intersection(*map(set, variants[1:])) if variants else set()
    names = {v: tradeoff_name(groups[v][0]) for v in variants}
    points = []
    for v, members in groups.items():
        label = names[v]
        if sum(n == label for n in names.values()) > 1:  # the same point configured differently: say how
            extras = [x for x in v if x not in shared and x.split("=", 1)[0].lstrip("+~") != "tradeoff"]
            label += " + " + " ".join(extras) if extras else ""
        costs = [_cost(r) for r in members]
        mean = {k: spread(c[k] for c in costs).mean for k in costs[0]}
        points.append(Point(label, tuple(sorted(r.seed for r in members)), **mean))
    everything = pareto_front(
        [(p.psnr, *(getattr(p, o.key) for o in OBJECTIVES)) for p in points], [True, *(o.maximise for o in OBJECTIVES)]
    )
    for p, on in zip(points, everything, strict=True):
        p.on_front = on
    for o in OBJECTIVES:
        for p, on in zip(
            points, pareto_front([(p.psnr, getattr(p, o.key)) for p in points], [True, o.maximise]), strict=True
        ):
            p.front[o.key] = on
    return sorted(points, key=lambda p: (not p.on_front, -p.psnr if not math.isnan(p.psnr) else math.inf, p.label))


# ------------------------------------------------------------------------------------------------ budgets
@dataclass(frozen=True)
class Budget:
    key: str
    op: str  # ">=" or "<="
    value: float

    def __str__(self) -> str:
        return f"{self.key}{self.op}{self.value:g}"

    def met_by(self, point: Point) -> bool:
        x = getattr(point, self.key)
        return not math.isnan(x) and {">=": operator.ge, "<=": operator.le}[self.op](x, self.value)


def parse_budget(text: str) -> Budget:
    """'fps>=60' -> Budget('fps', '>=', 60.0); keys: psnr, fps, train_min, peak_mib, model_mb."""
    m = re.fullmatch(r"\s*([a-z_]+)\s*(>=|<=)\s*([-+0-9.eE]+)\s*", text)
    if m is None or m.group(1) not in BUDGET_KEYS:
        raise ReportError(
            f"budget {text!r}: expected KEY>=NUMBER or KEY<=NUMBER with KEY one of "
            f"{', '.join(BUDGET_KEYS)}, e.g. fps>=60 or model_mb<=10."
        )
    try:
        return Budget(m.group(1), m.group(2), float(m.group(3)))
    except ValueError:
        raise ReportError(f"budget {text!r}: {m.group(3)!r} is not a number; write e.g. train_min<=5.") from None


def recommend(points: list[Point], budget: Budget) -> Point | None:
    """The point with the best novel-pose PSNR among those meeting the budget (None when none does)."""
    meeting = [p for p in points if budget.met_by(p) and not math.isnan(p.psnr)]
    return max(meeting, key=lambda p: (p.psnr, p.label), default=None)


# ------------------------------------------------------------------------------------------------ speed per dB
@dataclass(frozen=True)
class KnobGain:
    label: str
    db_lost: float  # baseline PSNR - point PSNR (negative: the knob gained quality)
    train_speedup: float  # baseline training time / point's
    fps_speedup: float  # point's render fps / baseline's
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


# ------------------------------------------------------------------------------------------------ text
def _fmt(x: float, digits: int = 2) -> str:
    return "-" if math.isnan(x) else f"{x:.{digits}f}"


def points_markdown(points: list[Point]) -> str:
    header = (
        "point",
        "seeds",
        "front",
        "novel-pose PSNR",
        "fps (novel pose)",
        "train min",
        "peak MiB",
        "model MB",
        "Gaussians",
    )
    rows = [
        (
            p.label,
            ",".join(map(str, p.seeds)),
            "yes" if p.on_front else "",
            _fmt(p.psnr),
            _fmt(p.fps, 1),
            _fmt(p.train_min),
            _fmt(p.peak_mib, 0),
            _fmt(p.model_mb, 3),
            _fmt(p.num_gaussians, 0),
        )
        for p in points
    ]
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


def to_markdown(points: list[Point], runs: list[Run], budgets: list[Budget], gains: list[KnobGain]) -> str:
    steps = sorted({int(r.record.get("steps", 0)) for r in runs})
    devices = sorted({str((r.record.get("render_fps") or {}).get("device")) for r in runs})
    parts = [
        "# Speed / size / accuracy trade-off",
        "",
        f"{len(runs)} runs, {len(points)} points; training steps {', '.join(map(str, steps))}; fps measured on "
        f"{', '.join(devices)}. Each number is the mean over the point's seeds. Front: on the Pareto front of all five "
        "columns (higher PSNR and fps, lower training time, memory and size); front members first, then by PSNR.",
        "",
        points_markdown(points),
        "",
        "## Recommendations",
        "",
    ]
    for b in budgets:
        best = recommend(points, b)
        text = "none meets it" if best is None else f"**{best.label}** ({_fmt(best.psnr)} dB novel-pose PSNR)"
        parts.append(f"- `{b}`: {text}")
    parts += ["", "## Speed per dB lost (single knobs against the baseline)", ""]
    if gains:
        parts += [
            "Speed doublings = log2(training speed-up) + log2(render fps speed-up); per dB lost = doublings / "
            '(baseline PSNR - point PSNR); "free" = less than 0.01 dB lost. Best first: the first three rows are '
            "the knobs that buy the most speed per dB.",
            "",
            gains_markdown(gains),
        ]
    else:
        parts.append(f"(no `{BASELINE}` point among the runs: nothing to compare the knobs with)")
    return "\n".join(parts) + "\n"


def to_csv(points: list[Point]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf)
    keys = ("psnr", "fps", "train_min", "peak_mib", "model_mb", "num_gaussians")
    w.writerow(["point", "seeds", "on_front", *keys, *(f"front_{o.key}" for o in OBJECTIVES)])
    for p in points:
        w.writerow(
            [
                p.label,
                " ".join(map(str, p.seeds)),
                int(p.on_front),
                *(getattr(p, k) for k in keys),
                *(int(p.front[o.key]) for o in OBJECTIVES),
            ]
        )
    return buf.getvalue()


# ------------------------------------------------------------------------------------------------ plots
def figure(points: list[Point], objective: Objective):
    """Novel-pose PSNR against one objective; the front of that plane joined by a line, every point labelled."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.0, 3.8))
    shown = [p for p in points if not math.isnan(p.psnr) and not math.isnan(getattr(p, objective.key))]
    for on, style in ((False, dict(c="0.6", s=18)), (True, dict(c="tab:red", s=30))):
        sel = [p for p in shown if p.front[objective.key] == on]
        ax.scatter(
            [getattr(p, objective.key) for p in sel],
            [p.psnr for p in sel],
            zorder=3,
            label="Pareto front" if on else "dominated",
            **style,
        )
    front = sorted((p for p in shown if p.front[objective.key]), key=lambda p: getattr(p, objective.key))
    ax.plot([getattr(p, objective.key) for p in front], [p.psnr for p in front], c="tab:red", lw=1, zorder=2)
    for p in shown:
        ax.annotate(p.label, (getattr(p, objective.key), p.psnr), fontsize=6, xytext=(3, 2), textcoords="offset points")
    xs = [getattr(p, objective.key) for p in shown]
    if xs and min(xs) > 0 and max(xs) / min(xs) > 20:
        ax.set_xscale("log")
    better = "right is better" if objective.maximise else "left is better"
    ax.set_xlabel(f"{objective.label} ({better})", fontsize=8)
    ax.set_ylabel("novel-pose PSNR (dB)", fontsize=8)
    ax.ticklabel_format(axis="y", useOffset=False)
    ax.tick_params(labelsize=7)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def write_report(runs: list[Run], out_dir: Path, budgets: list[str] | None = None) -> tuple[str, list[Path]]:
    """tradeoff.md, tradeoff.csv, tradeoff_<objective>.png and a TensorBoard log (tb/) in `out_dir`."""
    import matplotlib.pyplot as plt
    from torch.utils.tensorboard import SummaryWriter

    parsed = [parse_budget(b) for b in (budgets or DEFAULT_BUDGETS)]
    points = build_points(runs)
    gains = knob_gains(points)
    markdown = to_markdown(points, runs, parsed, gains)
    out_dir = Path(out_dir)
    paths = [
        atomic_write_text(out_dir / "tradeoff.md", markdown),
        atomic_write_text(out_dir / "tradeoff.csv", to_csv(points)),
    ]
    with SummaryWriter(log_dir=str(out_dir / "tb")) as writer:
        writer.add_text("tradeoff", markdown)
        for objective in OBJECTIVES:
            fig = figure(points, objective)
            paths.append(save_png(fig, out_dir / objective.file, dpi=100))
            writer.add_figure(f"tradeoff/{Path(objective.file).stem}", fig, close=False)
            plt.close(fig)
    paths.append(out_dir / "tb")
    return markdown, paths
