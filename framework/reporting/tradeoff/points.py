"""The trade-off's points and their Pareto fronts: one point per variant (runs that differ only by seed) with per-seed
costs, mean and std, and its fronts on the means and per seed, so a front that is one seed's accident shows. The
objectives and their planes live here because every other module of the report reads them, and so does the one rule
for which split the PSNR is judged on (`judged_split`)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from framework.reporting.pareto import pareto_front
from framework.reporting.runs import Run, group_runs
from framework.reporting.stats import Spread, spread

BASELINE = "baseline"
NOVEL_VIEW = "novel_view"
STORED_POSES = "novel_pose"  # the held-out motion with its stored poses (fitted; noisy on the realistic studio)
TRUE_POSES = "novel_pose_true_poses"  # the same motion with the true poses, recorded later (tools/record_true_poses.py)
#: the judged PSNR's label, by split (tables and plots)
PSNR_LABELS = {STORED_POSES: "novel-pose PSNR", TRUE_POSES: "novel-pose PSNR, true poses"}
#: PSNRs shown beside the judged one, never judged by: Point.stats key -> (split, label)
SIDE_PSNRS = {
    "psnr_stored_poses": (STORED_POSES, "novel-pose PSNR, stored poses"),
    "psnr_novel_view": (NOVEL_VIEW, "novel-view PSNR"),
}
ALL = "all"  # key of the front over all five objectives in Point.seed_front / seed_unstable


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
QUANTITIES = ("psnr", "fps", "fps_torch", "train_min", "peak_mib", "model_mb", "num_gaussians", *SIDE_PSNRS)


def judged_split(runs: Sequence[Run]) -> str:
    """The split whose whole-image PSNR every point is judged by (table, fronts, budgets, Δ, speed per dB): the
    held-out motion with the true poses (TRUE_POSES) when every run holds it, else with the stored poses. On the
    realistic studio the stored poses carry pose-fit noise that compresses and even flips differences between models
    (docs/results/table4.md, "Reading it"); the split is the same for every point, never mixed."""
    if runs and all(r.metric(TRUE_POSES, "image", "psnr") is not None for r in runs):
        return TRUE_POSES
    return STORED_POSES


def psnr_label(split: str) -> str:
    """The judged PSNR's label for `split` (PSNR_LABELS, else the split's name)."""
    return PSNR_LABELS.get(split, f"PSNR ({split})")


def side_psnrs(split: str) -> tuple[str, ...]:
    """The SIDE_PSNRS keys shown beside a PSNR judged on `split`: novel view always, the stored poses where they are
    not the judged split."""
    return tuple(k for k, (s, _) in SIDE_PSNRS.items() if s != split)


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
    split: str = STORED_POSES  # the split `psnr` is on (judged_split of the runs)

    psnr = _mean_of("psnr")  # novel-pose PSNR on `split` (whole image, dB)
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


def _cost(run: Run, split: str) -> dict[str, float]:
    r = run.record
    memory = r.get("cuda_peak_mib")
    return {
        "psnr": _number(run.metric(split, "image", "psnr")),
        "fps": viewer_fps(r, "compiled"),
        "fps_torch": viewer_fps(r, "torch"),
        "train_min": _number(r.get("train_seconds")) / 60,
        "peak_mib": _number(memory if memory is not None else r.get("peak_rss_mib")),
        "model_mb": _number(r.get("model_bytes")) / 1e6,
        "num_gaussians": _number(r.get("num_gaussians")),
        **{k: _number(run.metric(s, "image", "psnr")) for k, (s, _) in SIDE_PSNRS.items()},
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


def points_split(points: Sequence[Point]) -> str:
    """The split the points' PSNR is on (STORED_POSES for no points); points judged on different splits are an
    error, never a table."""
    splits = {p.split for p in points}
    if len(splits) > 1:
        raise ValueError(f"points judged on different splits {sorted(splits)}; build them together (build_points)")
    return splits.pop() if splits else STORED_POSES


def build_points(runs: list[Run], split: str | None = None) -> list[Point]:
    """One point per variant, means and stds over seeds, with every front computed (mean and per seed); PSNR on
    `split`, by default judged_split(runs)."""
    split = judged_split(runs) if split is None else split
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
        per_seed = {r.seed: _cost(r, split) for r in members}
        stats = {k: spread(c[k] for c in per_seed.values()) for k in QUANTITIES}
        choice = tradeoff_choice(members[0])
        points.append(Point(label, tuple(sorted(per_seed)), choice, extras, per_seed, stats, split=split))
    mark_fronts(points)
    return sorted(points, key=lambda p: (not p.on_front, -p.psnr if not math.isnan(p.psnr) else math.inf, p.label))
