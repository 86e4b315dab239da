"""The speed / size / accuracy trade-off (sweeps/tradeoff.yaml) from the runs' results.json: novel-pose PSNR against
viewer fps (novel pose, the compiled CPU path), training time, peak memory and model size.

A point is a variant (`framework.reporting.runs`: runs that differ only by seed), labelled by its trade-off config
(`+tradeoff=NAME`) or, for runs outside the trade-off sweep, by its experiment. Every number is the mean over its
seeds, and each point keeps the std over seeds too, because with two or three seeds a front can be an accident of
one seed: fronts are also computed per seed, and points whose membership depends on the seed are marked. Written:
one PNG per plane with that plane's Pareto front marked and error bars (maximise PSNR and fps, minimise the others),
the same plots in TensorBoard, a Markdown table with the front over all five objectives first, a CSV, the best
measured point for each budget (`'budgets=["fps>=60"]'`) with the config to paste (also recommendations.csv), and
the knobs that buy the most speed per dB lost.

fps is `viewer_fps` of results.json (written after training by the viewer benchmark): `paths.compiled.novel_pose`
(numba rasterizer and compiled CPU kernels) is the `fps` objective; `paths.torch.novel_pose` (torch_ref rasterizer,
torch kernels) is shown as `fps_torch` but is no objective. Runs without `viewer_fps` have NaN for both.
"""

from __future__ import annotations

import csv
import io
import math
import operator
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from framework.atomic import atomic_write_text
from framework.plugins import format_table
from framework.reporting.figures import save_png
from framework.reporting.pareto import pareto_front
from framework.reporting.runs import ReportError, Run, group_runs
from framework.reporting.stats import Difference, Spread, difference, spread

BASELINE = "baseline"
PRESET_PREFIX = "preset_"
COMPACT_SUFFIX = "_compact"  # a trade-off point trained as usual, then compacted with framework.prune
PRUNE_STEP = "python -m framework.prune ckpt=<run>/checkpoints/final.ckpt"
PSNR = ("novel_pose", "image", "psnr")  # the quality every point is judged by
LOSS_NOISE_DB = 0.01  # a PSNR loss below this counts as none (the metric's own rounding noise)
ALL = "all"  # key of the front over all five objectives in Point.seed_front / seed_unstable
NONE_MEETS = "none measured meets it"


@dataclass(frozen=True)
class Objective:
    key: str  # attribute of Point, and the name a budget uses
    label: str
    maximise: bool
    file: str  # the plot's PNG name


OBJECTIVES = (
    Objective("fps", "viewer fps, novel pose, compiled CPU path", True, "tradeoff_fps.png"),
    Objective("train_min", "training time (min)", False, "tradeoff_train_time.png"),
    Objective("peak_mib", "peak training memory (MiB)", False, "tradeoff_memory.png"),
    Objective("model_mb", "model size (MB, learned tensors)", False, "tradeoff_model_size.png"),
)
#: shown and plotted, but no objective: the torch_ref path is what runs where nothing is compiled
FPS_TORCH = Objective("fps_torch", "viewer fps, novel pose, torch_ref path", True, "tradeoff_fps_torch.png")
PLANES = (*OBJECTIVES, FPS_TORCH)  # the (PSNR, x) planes that get a front and a plot
DEFAULT_BUDGETS = ("train_min<=2", "train_min<=5", "train_min<=10", "fps>=30", "fps>=60", "fps>=120")
QUANTITIES = ("psnr", "fps", "fps_torch", "train_min", "peak_mib", "model_mb", "num_gaussians")
BUDGET_KEYS = ("psnr", *(o.key for o in PLANES))


def _mean_of(key: str) -> property:
    return property(lambda self: self.stats[key].mean, doc=f"mean of {key} over the point's seeds")


@dataclass
class Point:
    """One variant: per-seed values, their mean and std (`stats`), and its fronts (mean and per seed)."""

    label: str
    seeds: tuple[int, ...]
    choice: tuple[str, str]  # the config group and option that chose the point: ("tradeoff", "sh0")
    extras: tuple[str, ...]  # other overrides that tell this point from another of the same choice
    per_seed: dict[int, dict[str, float]]  # seed -> quantity -> value
    stats: dict[str, Spread]  # quantity -> mean and std over seeds
    on_front: bool = False  # on the front of all five objectives (means)
    front: dict[str, bool] = field(default_factory=dict)  # plane key -> on the (PSNR, x) front (means)
    seed_front: dict[str, dict[int, bool]] = field(default_factory=dict)  # ALL or plane key -> seed -> on it
    seed_unstable: dict[str, bool] = field(default_factory=dict)  # ALL or plane key -> membership depends on seed

    psnr = _mean_of("psnr")  # novel-pose PSNR (whole image, dB)
    fps = _mean_of("fps")  # viewer fps, novel pose, compiled path
    fps_torch = _mean_of("fps_torch")  # viewer fps, novel pose, torch_ref path
    train_min = _mean_of("train_min")  # training wall time (minutes)
    peak_mib = _mean_of("peak_mib")  # peak memory of the fit loop: CUDA allocated where measured, else RSS
    model_mb = _mean_of("model_mb")  # learned tensors, 10^6 bytes
    num_gaussians = _mean_of("num_gaussians")

    def std(self, key: str) -> float:
        """Sample std over seeds (NaN with one seed)."""
        return self.stats[key].std


def _number(value: Any) -> float:
    return math.nan if value is None else float(value)


def viewer_fps(record: Mapping[str, Any], path: str, split: str = "novel_pose") -> float:
    """viewer_fps.paths[path][split] of a run record, NaN when the run has no viewer measurement."""
    paths = (record.get("viewer_fps") or {}).get("paths") or {}
    return _number((paths.get(path) or {}).get(split))


def _cost(run: Run) -> dict[str, float]:
    r = run.record
    memory = r.get("cuda_peak_mib")
    return {
        "psnr": _number(run.metric(*PSNR)),
        "fps": viewer_fps(r, "compiled"),
        "fps_torch": viewer_fps(r, "torch"),
        "train_min": _number(r.get("train_seconds")) / 60,
        "peak_mib": _number(memory if memory is not None else r.get("peak_rss_mib")),
        "model_mb": _number(r.get("model_bytes")) / 1e6,
        "num_gaussians": _number(r.get("num_gaussians")),
    }


def tradeoff_choice(run: Run) -> tuple[str, str]:
    """The group and option that chose the run's point: `+tradeoff=NAME` among its overrides, else
    `+experiment=NAME`, else the run's experiment (its task name)."""
    found = {}
    for item in run.variant:
        key, _, value = item.partition("=")
        found.setdefault(key.lstrip("+~"), value)
    for group in ("tradeoff", "experiment"):
        if group in found:
            return group, found[group]
    return "experiment", run.experiment


def tradeoff_name(run: Run) -> str:
    """The run's trade-off point (`+tradeoff=NAME` among its overrides), else its experiment."""
    group, name = tradeoff_choice(run)
    return name if group == "tradeoff" else run.experiment


# ------------------------------------------------------------------------------------------------ fronts
def _maximise(keys: Sequence[str]) -> list[bool]:
    by_key = {o.key: o.maximise for o in PLANES}
    return [True, *(by_key[k] for k in keys)]


def _front_keys() -> dict[str, tuple[str, ...]]:
    """Front name -> the objectives beside PSNR it is taken over: ALL (the five) and one per plane."""
    return {ALL: tuple(o.key for o in OBJECTIVES), **{o.key: (o.key,) for o in PLANES}}


def _front(rows: Sequence[Mapping[str, float]], keys: Sequence[str]) -> list[bool]:
    return pareto_front([(r["psnr"], *(r[k] for k in keys)) for r in rows], _maximise(keys))


def _measured_on(point: Point, seed: int, keys: Sequence[str]) -> bool:
    values = point.per_seed.get(seed)
    return values is not None and not any(math.isnan(values[k]) for k in ("psnr", *keys))


def _seed_fronts(points: list[Point], keys: Sequence[str]) -> list[dict[int, bool]]:
    """For each point, seed -> whether it is on that seed's front, taken over the points measured on that seed (a
    point lacking the seed, or a value on it, is left out of that seed's front rather than counted as off it)."""
    out: list[dict[int, bool]] = [{} for _ in points]
    for s in sorted({s for p in points for s in p.seeds}):
        having = [i for i, p in enumerate(points) if _measured_on(p, s, keys)]
        for i, on in zip(having, _front([points[i].per_seed[s] for i in having], keys), strict=True):
            out[i][s] = on
    return out


def mark_fronts(points: list[Point]) -> None:
    """Fill each point's fronts: on the means, then per seed, and `seed_unstable` where the memberships (the seeds'
    and the mean's) disagree: with few seeds a front can be one seed's accident."""
    means = [{k: p.stats[k].mean for k in QUANTITIES} for p in points]
    for name, keys in _front_keys().items():
        per_seed = _seed_fronts(points, keys)
        for p, on, seeds_on in zip(points, _front(means, keys), per_seed, strict=True):
            if name == ALL:
                p.on_front = on
            else:
                p.front[name] = on
            p.seed_front[name] = seeds_on
            p.seed_unstable[name] = len({on, *seeds_on.values()}) > 1


def front_label(point: Point) -> str:
    """The table's front cell: 'yes' on every seed's front too, 'yes*' on the mean front but not every seed's."""
    if not point.on_front:
        return ""
    return "yes*" if point.seed_unstable[ALL] else "yes"


def psnr_flips(points: list[Point], key: str) -> list[tuple[str, str]]:
    """Neighbours along the (PSNR, key) front (ordered by key) whose PSNR order differs between seeds: the front's
    shape there is within seed noise. Seeds that only one of the pair has, and ties, are left out."""
    front = sorted((p for p in points if p.front[key]), key=lambda p: (getattr(p, key), p.label))
    flips = []
    for a, b in zip(front, front[1:], strict=False):
        signs = set()
        for s in set(a.per_seed) & set(b.per_seed):
            d = a.per_seed[s]["psnr"] - b.per_seed[s]["psnr"]
            if not math.isnan(d) and d != 0:
                signs.add(d > 0)
        if len(signs) > 1:
            flips.append((a.label, b.label))
    return flips


def build_points(runs: list[Run]) -> list[Point]:
    """One point per variant, means and stds over seeds, with every front computed (mean and per seed)."""
    groups = group_runs(runs)
    variants = list(groups)
    shared = set(variants[0]).intersection(*map(set, variants[1:])) if variants else set()
    names = {v: tradeoff_name(groups[v][0]) for v in variants}
    points = []
    for v, members in groups.items():
        label = names[v]
        extras: tuple[str, ...] = ()
        if sum(n == label for n in names.values()) > 1:  # the same point configured differently: say how
            extras = tuple(x for x in v if x not in shared and x.split("=", 1)[0].lstrip("+~") != "tradeoff")
            label += " + " + " ".join(extras) if extras else ""
        per_seed = {r.seed: _cost(r) for r in members}
        stats = {k: spread(c[k] for c in per_seed.values()) for k in QUANTITIES}
        choice = tradeoff_choice(members[0])
        points.append(Point(label, tuple(sorted(per_seed)), choice, extras, per_seed, stats))
    mark_fronts(points)
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
    """'fps>=60' -> Budget('fps', '>=', 60.0); keys: psnr, fps, train_min, peak_mib, model_mb, fps_torch."""
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
    """The measured point with the best mean novel-pose PSNR among those whose mean meets the budget (None when none
    does). No interpolation between points: a user can only train a config that was measured."""
    meeting = [p for p in points if budget.met_by(p) and not math.isnan(p.psnr)]
    return max(meeting, key=lambda p: (p.psnr, p.label), default=None)


def conf_dir() -> Path:
    """The config folder Hydra composes from (`pkg://framework.conf`: conf/ in a checkout, shipped inside the
    package when installed), so the report finds the presets wherever splatrig runs from."""
    from importlib import resources

    return Path(str(resources.files("framework.conf")))


def _defaults_entries(path: Path) -> list[str]:
    """A config's defaults list as 'group/option' strings ('/tradeoff/sh0' for `- /tradeoff/sh0` or
    `- /tradeoff: sh0`)."""
    import yaml

    node = yaml.safe_load(path.read_text())
    entries = (node.get("defaults") or []) if isinstance(node, dict) else []
    out = []
    for entry in entries:
        if isinstance(entry, str):
            out.append(entry)
        elif isinstance(entry, dict) and len(entry) == 1:
            ((group, option),) = entry.items()
            out.append(f"{group}/{option}")
    return out


def presets_by_point(conf: Path | None = None) -> dict[str, str]:
    """Trade-off point -> the preset (conf/preset/<name>.yaml) whose defaults include `/tradeoff/<point>`: a preset is
    a trade-off point with a header, the name a user should paste. The first preset by name wins."""
    folder = (conf_dir() if conf is None else Path(conf)) / "preset"
    out: dict[str, str] = {}
    for path in sorted(folder.glob("*.yaml")):
        for entry in _defaults_entries(path):
            if entry.startswith("/tradeoff/"):
                out.setdefault(entry.removeprefix("/tradeoff/"), path.stem)
    return out


def paste_steps(point: Point, presets: Mapping[str, str]) -> tuple[str, ...]:
    """What to paste to get the point: its override (a preset's name where one wraps it), and for a compacted point
    (`<point>_compact`) the prune command after training."""
    group, name = point.choice
    base = name.removesuffix(COMPACT_SUFFIX)
    choice = f"+preset={presets[base]}" if group == "tradeoff" and base in presets else f"+{group}={base}"
    steps = (" ".join((choice, *point.extras)),)
    return (*steps, PRUNE_STEP) if name.endswith(COMPACT_SUFFIX) else steps


@dataclass(frozen=True)
class Recommendation:
    budget: Budget
    point: Point | None  # None: no measured point meets the budget
    paste: tuple[str, ...]  # the commands, in order
    delta: Difference | None  # novel-pose PSNR minus the baseline's, with its seed noise; None without a baseline


def recommendations(points: list[Point], budgets: list[Budget], presets: Mapping[str, str]) -> list[Recommendation]:
    """The best point for each budget, with what to paste and how it compares with the baseline."""
    base = next((p for p in points if p.label == BASELINE), None)
    out = []
    for b in budgets:
        best = recommend(points, b)
        if best is None:
            out.append(Recommendation(b, None, (), None))
            continue
        delta = None if base is None else difference(best.stats["psnr"], base.stats["psnr"])
        out.append(Recommendation(b, best, paste_steps(best, presets), delta))
    return out


# ------------------------------------------------------------------------------------------------ speed per dB
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


# ------------------------------------------------------------------------------------------------ text
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


def caption(points: list[Point], runs: list[Run]) -> str:
    """How the table was measured: runs, steps, the viewer benchmark's settings, the seeds per point."""
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
        f"is the mean over the point's seeds (PSNR: mean ± sample std). {fps}"
    )


def points_markdown(points: list[Point], fps_headers: tuple[str, str]) -> str:
    header = (
        "point",
        "seeds",
        "front",
        "novel-pose PSNR",
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


def recommendations_markdown(recs: list[Recommendation], fps_headers: tuple[str, str]) -> str:
    header = (
        "budget",
        "point",
        "config to paste",
        "novel-pose PSNR",
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
        "For each budget, the measured point with the best mean novel-pose PSNR whose mean meets it (no "
        "interpolation between points). Δ dB vs baseline = mean difference ± sqrt(s_p²/n_p + s_b²/n_b) over seeds; "
        "`<run>` is the folder your training run wrote.",
        "",
        recommendations_markdown(recs, fps_headers),
        "",
        "## Speed per dB lost (single knobs against the baseline)",
        "",
    ]
    if gains:
        parts += [
            "Speed doublings = log2(training speed-up) + log2(viewer fps speed-up, compiled path); per dB lost = "
            'doublings / (baseline PSNR - point PSNR); "free" = less than 0.01 dB lost. Best first: the first three '
            "rows are the knobs that buy the most speed per dB.",
            "",
            gains_markdown(gains),
        ]
    elif any(p.label == BASELINE for p in points):
        parts.append(f"(no point besides `{BASELINE}`: no knob to compare with it)")
    else:
        parts.append(f"(no `{BASELINE}` point among the runs: nothing to compare the knobs with)")
    return "\n".join(parts) + "\n"


def to_csv(points: list[Point]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(
        [
            "point",
            "seeds",
            "on_front",
            "front_seed_unstable",
            *QUANTITIES,
            *(f"{k}_std" for k in QUANTITIES),
            *(f"front_{o.key}" for o in PLANES),
            *(f"seed_unstable_{o.key}" for o in PLANES),
        ]
    )
    for p in points:
        w.writerow(
            [
                p.label,
                " ".join(map(str, p.seeds)),
                int(p.on_front),
                int(p.seed_unstable[ALL]),
                *(p.stats[k].mean for k in QUANTITIES),
                *(p.std(k) for k in QUANTITIES),
                *(int(p.front[o.key]) for o in PLANES),
                *(int(p.seed_unstable[o.key]) for o in PLANES),
            ]
        )
    return buf.getvalue()


def recommendations_csv(recs: list[Recommendation]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(
        [
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
        ]
    )
    for r in recs:
        p = r.point
        if p is None:
            w.writerow([str(r.budget), NONE_MEETS, *[""] * 9])
            continue
        d = r.delta or Difference(math.nan, math.nan)
        w.writerow(
            [
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
            ]
        )
    return buf.getvalue()


# ------------------------------------------------------------------------------------------------ plots
def _err(values: list[float]) -> list[float]:
    """Error-bar half widths: a std over seeds, none drawn (0) where one seed left it unknown."""
    return [0.0 if math.isnan(v) else v for v in values]


def figure(points: list[Point], objective: Objective):
    """Novel-pose PSNR against one objective, with error bars (std over seeds) on both axes; the front of that plane
    joined by a line, its members filled when they are on every seed's front and hollow when not; every point
    labelled."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    key = objective.key
    fig, ax = plt.subplots(figsize=(5.0, 3.8))
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
    ax.set_ylabel("novel-pose PSNR (dB)", fontsize=8)
    ax.ticklabel_format(axis="y", useOffset=False)
    ax.tick_params(labelsize=7)
    ax.grid(alpha=0.3)
    if shown:
        ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def write_report(runs: list[Run], out_dir: Path, budgets: list[str] | None = None) -> tuple[str, list[Path]]:
    """tradeoff.md, tradeoff.csv, recommendations.csv, tradeoff_<plane>.png and a TensorBoard log (tb/) in
    `out_dir`."""
    import matplotlib.pyplot as plt
    from torch.utils.tensorboard import SummaryWriter

    parsed = [parse_budget(b) for b in (budgets or DEFAULT_BUDGETS)]
    points = build_points(runs)
    recs = recommendations(points, parsed, presets_by_point())
    markdown = to_markdown(points, runs, recs, knob_gains(points))
    out_dir = Path(out_dir)
    paths = [
        atomic_write_text(out_dir / "tradeoff.md", markdown),
        atomic_write_text(out_dir / "tradeoff.csv", to_csv(points)),
        atomic_write_text(out_dir / "recommendations.csv", recommendations_csv(recs)),
    ]
    with SummaryWriter(log_dir=str(out_dir / "tb")) as writer:
        writer.add_text("tradeoff", markdown)
        for objective in PLANES:
            fig = figure(points, objective)
            paths.append(save_png(fig, out_dir / objective.file, dpi=100))
            writer.add_figure(f"tradeoff/{Path(objective.file).stem}", fig, close=False)
            plt.close(fig)
    paths.append(out_dir / "tb")
    return markdown, paths
