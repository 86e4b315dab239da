"""The report kinds `python -m framework.report --kind NAME` knows. A kind is a function (runs, out_dir) ->
(markdown to print, paths written); every kind reads the same runs (`framework.reporting.runs`), so adding one
(e.g. a training-time / quality trade-off) is one module and one line here."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from framework.reporting import table4
from framework.reporting.runs import Run

ReportKind = Callable[[list[Run], Path], tuple[str, list[Path]]]

REPORT_KINDS: dict[str, ReportKind] = {
    "table4": table4.write_report,
}
