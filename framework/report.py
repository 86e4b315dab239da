"""`python -m framework.report <sweep dir> [<sweep dir> ...] [--kind table4] [--out DIR]`: one report over the runs
of one or more sweep directories (a sweep run in parts), from the results.json every run writes.

table4 (default): the paper's ablation table with seed statistics and verdicts, as Markdown, CSV and PNG, plus a
TensorBoard log; see `framework.reporting.table4`.

tradeoff: novel-pose PSNR against render fps, training time, peak memory and model size (sweeps/tradeoff.yaml):
Pareto plots, the table sorted by the front, the best point per budget (`--budget fps>=60`, repeatable) and the
speed bought per dB lost; see `framework.reporting.tradeoff`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from framework.errors import reported_as_message


def main(argv: list[str] | None = None) -> int:
    from framework.reporting.kinds import REPORT_KINDS

    ap = argparse.ArgumentParser(prog="python -m framework.report", description=__doc__.split("\n\n")[0])
    ap.add_argument("dirs", nargs="+", help="sweep (or run) directories; searched recursively for results.json")
    ap.add_argument("--kind", default="table4", choices=sorted(REPORT_KINDS), help="which report (default table4)")
    ap.add_argument("--out", default=None, help="output directory (default: <first dir>/report)")
    ap.add_argument(
        "--budget",
        action="append",
        default=None,
        metavar="KEY>=X|KEY<=X",
        help="tradeoff: a budget to recommend for (repeatable; keys psnr, fps, train_min, peak_mib, "
        "model_mb; default fps>=60, train_min<=5, model_mb<=10)",
    )
    args = ap.parse_args(argv)
    if args.budget and args.kind != "tradeoff":
        ap.error("--budget applies to --kind tradeoff only")
    with reported_as_message():
        from framework.reporting.runs import find_runs

        runs = find_runs(args.dirs)
        out = Path(args.out) if args.out else Path(args.dirs[0]) / "report"
        options = {"budgets": args.budget} if args.budget else {}
        markdown, paths = REPORT_KINDS[args.kind](runs, out, **options)
        print(markdown)
        print(f"[splatrig] {len(runs)} runs; written: " + ", ".join(str(p) for p in paths), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
