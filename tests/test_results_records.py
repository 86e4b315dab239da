"""The published result tables are what the report makes from the run records committed beside them: a table edited
by hand, or records that went missing, fail here. (The CSVs are compared; the Markdown and plots come from the same
table.)"""

from __future__ import annotations

from pathlib import Path

import pytest

from framework.reporting.kinds import REPORT_KINDS
from framework.reporting.runs import find_runs

RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results"
#: (report kind, the records, the published CSV)
PUBLISHED = (
    ("table4", [RESULTS / "table4_cpu" / "runs"], RESULTS / "table4_cpu" / "table4.csv"),
    ("tradeoff", [RESULTS / "tradeoff_cpu" / "runs"], RESULTS / "tradeoff_cpu" / "tradeoff.csv"),
    (
        "paper_forms",  # paper_full's runs are Table 4's
        [
            RESULTS / "paper_forms_cpu" / "realistic" / "runs",
            *(RESULTS / "table4_cpu" / "runs").glob("*/*_paper_full_seed*"),
        ],
        RESULTS / "paper_forms_cpu" / "realistic" / "paper_forms.csv",
    ),
)


@pytest.mark.parametrize(("kind", "records", "published"), PUBLISHED, ids=[p[0] for p in PUBLISHED])
def test_published_table_is_the_report_of_its_records(kind: str, records: list[Path], published: Path, tmp_path):
    REPORT_KINDS[kind](find_runs(records), tmp_path)
    assert (tmp_path / published.name).read_text() == published.read_text()
