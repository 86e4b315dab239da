"""`python -m framework.report runs=DIR [kind=tradeoff] [out=DIR]`: one report over the runs of one or more sweep
directories (a sweep run in parts: `runs=[DIR1,DIR2]`), from the results.json every run writes.

table4 (default): the paper's ablation table with seed statistics and verdicts, as Markdown, CSV and PNG, plus a
TensorBoard log; see `framework.reporting.table4`.

tradeoff: novel-pose PSNR against viewer fps (compiled CPU path), training time, peak memory and model size
(sweeps/tradeoff.yaml): Pareto plots with seed error bars, the table sorted by the front, the best measured point per
budget with the config to paste (`'budgets=["fps>=60",...]'`) and the speed bought per dB lost; see
`framework.reporting.tradeoff`.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

from framework.errors import SplatrigError, reported_as_message


def report(
    runs: Sequence[str | Path], kind: str = "table4", out: str | Path | None = None, budgets: Sequence[str] = ()
) -> list[Path]:
    """Write the `kind` report of the runs under `runs` to `out` (default <first folder>/report), print its Markdown,
    and return the paths written."""
    from framework.reporting.kinds import REPORT_KINDS
    from framework.reporting.runs import find_runs

    if kind not in REPORT_KINDS:
        raise SplatrigError(f"kind={kind}: no such report; kinds: {', '.join(sorted(REPORT_KINDS))}")
    if budgets and kind != "tradeoff":
        raise SplatrigError(f"budgets= applies to kind=tradeoff only (this is kind={kind}); leave it out")
    if not runs:
        raise SplatrigError("runs=: name at least one sweep or run folder (runs=DIR or runs=[DIR1,DIR2])")
    found = find_runs([str(r) for r in runs])
    folder = Path(out) if out else Path(runs[0]) / "report"
    options = {"budgets": list(budgets)} if budgets else {}
    markdown, paths = REPORT_KINDS[kind](found, folder, **options)
    print(markdown)
    print(f"[splatrig] {len(found)} runs; written: " + ", ".join(str(p) for p in paths), file=sys.stderr)
    return paths


def _as_list(value) -> list[str]:
    """A config value that is one string or a list of them."""
    if value is None:
        return []
    if isinstance(value, str):
        return [value]
    return [str(v) for v in value]


def main() -> int:
    from omegaconf import DictConfig

    from framework.cli import hydra_main

    @hydra_main("report")
    def _main(cfg: DictConfig) -> None:
        with reported_as_message():
            report(_as_list(cfg.runs), str(cfg.kind), cfg.out, _as_list(cfg.budgets))

    _main()
    return 0


if __name__ == "__main__":
    sys.exit(main())
