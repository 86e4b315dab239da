"""Budgets and what to train for each: parse a budget (`fps>=60`), pick the best measured point that meets it, and the
config to paste for it (a preset's name where conf/preset/ wraps the point, the prune command for a compacted
point), with its PSNR difference from the baseline."""

from __future__ import annotations

import math
import operator
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from framework.reporting.runs import ReportError
from framework.reporting.stats import Difference, difference
from framework.reporting.tradeoff.points import BASELINE, PLANES, Point

COMPACT_SUFFIX = "_compact"  # a trade-off point trained as usual, then compacted with framework.prune
PRUNE_STEP = "python -m framework.prune ckpt=<run>/checkpoints/final.ckpt"
DEFAULT_BUDGETS = ("train_min<=2", "train_min<=5", "train_min<=10", "fps>=30", "fps>=60", "fps>=120")
BUDGET_KEYS = ("psnr", *(o.key for o in PLANES))


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
    """The measured point with the best mean PSNR (the points' judged split) among those whose mean meets the budget
    (None when none does). No interpolation between points: a user can only train a config that was measured."""
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
    delta: Difference | None  # PSNR (judged split) minus the baseline's, with its seed noise; None without a baseline


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
