"""`python -m framework.report <sweep dir> [<sweep dir> ...] [--kind table4] [--out DIR]`: one report over the runs
of one or more sweep directories (a sweep run in parts), from the results.json every run writes.

table4 (default): the paper's ablation table with seed statistics and verdicts, as Markdown, CSV and PNG, plus a
TensorBoard log; see `framework.reporting.table4`.
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
    args = ap.parse_args(argv)
    with reported_as_message():
        from framework.reporting.runs import find_runs

        runs = find_runs(args.dirs)
        out = Path(args.out) if args.out else Path(args.dirs[0]) / "report"
        markdown, paths = REPORT_KINDS[args.kind](runs, out)
        print(markdown)
        print(f"[splatrig] {len(runs)} runs; written: " + ", ".join(str(p) for p in paths), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
