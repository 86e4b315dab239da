"""The report kinds `python -m framework.report kind=NAME` knows. A kind is a function (runs, out_dir) ->
(markdown to print, paths written); every kind reads the same runs (`framework.reporting.runs`), so adding one is one
module and one line here. Kinds that take options (tradeoff: `budgets`) get them as keyword arguments."""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from pathlib import Path

from framework.reporting import table4, tradeoff

ReportKind = Callable[..., tuple[str, list[Path]]]  # (runs: list[Run], out_dir: Path, **options)

REPORT_KINDS: dict[str, ReportKind] = {
    "table4": table4.write_report,
    "tradeoff": tradeoff.write_report,
    # sweeps/paper_forms.yaml: each of the project's forms against paper_full, judged better / worse / within noise
    "paper_forms": partial(
        table4.write_report, name="paper_forms", title="The project's forms against the paper's (paper_full)"
    ),
}
