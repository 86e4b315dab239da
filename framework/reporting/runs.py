"""Collecting runs: every results.json under the given directories, grouped into variants (runs that differ only by
their seed), so a report can put mean and spread over seeds in one cell.

A variant is the run's overrides without the seed and without keys that do not change what is trained (where files
go, logging, progress bars, threads). Two sweep parts launched with the same command give the same variants, so a
sweep run in several pieces reports as one.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from framework.errors import SplatrigError
from framework.evaluation.run_record import FILENAME, load_run_record

#: override keys (before "=") that do not change the trained model
NOT_VARIANT_KEYS = (
    "seed",
    "paths.",
    "hydra.",
    "callbacks.",
    "logger",
    "threads",
    "small_work_threads",
    "ckpt",
    "ckpt_path",
    "data_loader.",
    "data.workers",
    "eval.val_max_items",
)


class ReportError(SplatrigError):
    """The runs given to a report cannot make it (none found, mixed settings, ...)."""


@dataclass(frozen=True)
class Run:
    path: Path  # the run directory (holding results.json)
    experiment: str
    seed: int
    variant: tuple[str, ...]  # sorted overrides that define what was trained, seed excluded
    record: dict[str, Any] = field(repr=False)

    def metric(self, split: str, region: str, name: str) -> float | None:
        """metrics[split][region][name], or None when the run did not measure it."""
        value = self.record.get("metrics", {}).get(split, {}).get(region, {}).get(name)
        return None if value is None else float(value)


def variant_of(overrides: Iterable[str]) -> tuple[str, ...]:
    """The overrides that define the trained model: seed and bookkeeping keys dropped, sorted."""
    kept = []
    for item in overrides:
        key = item.split("=", 1)[0].lstrip("+~")
        if not any(key == k or (k.endswith(".") and key.startswith(k)) for k in NOT_VARIANT_KEYS):
            kept.append(item)
    return tuple(sorted(kept))


def find_runs(dirs: Sequence[str | Path]) -> list[Run]:
    """Every run record under `dirs` (searched recursively), sorted by experiment, variant and seed."""
    runs: list[Run] = []
    for d in dirs:
        root = Path(d)
        if not root.exists():
            raise ReportError(f"{root}: no such directory; give the sweep directories the runs wrote into.")
        for path in sorted(root.rglob(FILENAME)):
            record = load_run_record(path)
            runs.append(
                Run(
                    path=path.parent,
                    experiment=str(record["experiment"]),
                    seed=int(record["seed"]),
                    variant=variant_of(record.get("overrides", [])),
                    record=record,
                )
            )
    if not runs:
        raise ReportError(
            f"no {FILENAME} found under {', '.join(str(d) for d in dirs)}; each training run writes one into its "
            f"directory when it finishes, so run the sweep (or wait for it to finish) first."
        )
    return sorted(runs, key=lambda r: (r.experiment, r.variant, r.seed))


def group_runs(runs: Iterable[Run]) -> dict[tuple[str, ...], list[Run]]:
    """variant -> its runs (one per seed); a seed found twice in one variant is an error (the same job twice)."""
    groups: dict[tuple[str, ...], list[Run]] = {}
    for run in runs:
        members = groups.setdefault(run.variant, [])
        twin = next((r for r in members if r.seed == run.seed), None)
        if twin is not None:
            raise ReportError(
                f"seed {run.seed} of {run.experiment} ({', '.join(run.variant)}) was run twice: {twin.path} and "
                f"{run.path}; pass only one of the sweep directories that hold it, or delete one run."
            )
        members.append(run)
    return groups
