"""The one CSV writer the reports share: a header and rows to text, so every report's CSV quotes and ends lines
the same way (csv's dialect, not hand-joined commas)."""

from __future__ import annotations

import csv
import io
from collections.abc import Iterable, Sequence


def csv_text(header: Sequence[str], rows: Iterable[Sequence[object]]) -> str:
    """`header` then each row, as CSV text."""
    buf = io.StringIO()
    writer = csv.writer(buf)
    writer.writerow(header)
    writer.writerows(rows)
    return buf.getvalue()
