"""docs/errors.md is checked by the tests that produce its messages, so it cannot go stale.

Each table row is `| case | entry point | bad input | message |`. A test that triggers a case calls
`check_documented(case, entry, bad_input, message)`: the message is normalised (temporary folders -> `<tmp>`, run
timestamps -> `<run>`) and must equal the row's, and the row's entry point and input must be those given. After
changing a message on purpose, rewrite the rows and review the diff:

    SPLATRIG_UPDATE_ERRORS_DOC=1 python -m pytest tests/test_bad_input.py tests/test_divergence.py
"""

from __future__ import annotations

import os
import re
from pathlib import Path

DOC = Path(__file__).resolve().parents[1] / "docs" / "errors.md"
UPDATE_ENV = "SPLATRIG_UPDATE_ERRORS_DOC"
HEADER = "| case | entry point | bad input | message |"
_ROW = re.compile(r"^\| `(?P<case>[a-z0-9_]+)` \| (?P<entry>[^|]+) \| (?P<input>(?:[^|\\]|\\\|)+) \| (?P<msg>.*) \|$")


def normalise(message: str, roots: dict[str, str | os.PathLike]) -> str:
    """One line, with the given folders replaced by their names (`{"<tmp>": tmp_path}`) and run stamps by <run>."""
    text = " ".join(line.strip() for line in message.strip().splitlines() if line.strip())
    for name, root in sorted(roots.items(), key=lambda kv: -len(str(kv[1]))):
        text = text.replace(str(Path(root).resolve()), name).replace(str(root), name)
    return re.sub(r"\d{4}-\d{2}-\d{2}_\d{2}-\d{2}-\d{2}", "<run>", text)


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def rows() -> dict[str, tuple[str, str, str]]:
    """case -> (entry point, bad input, message) as written in docs/errors.md."""
    out = {}
    for line in DOC.read_text().splitlines():
        m = _ROW.match(line)
        if m:
            out[m["case"]] = (m["entry"].strip(), m["input"].strip(), m["msg"].strip().replace("\\|", "|"))
    return out


def check_documented(case: str, entry: str, bad_input: str, message: str) -> None:
    """The row of `case` says exactly this (or, with SPLATRIG_UPDATE_ERRORS_DOC=1, is rewritten to say it)."""
    line = f"| `{case}` | {entry} | {_cell(bad_input)} | {_cell(message)} |"
    if os.environ.get(UPDATE_ENV):
        lines = DOC.read_text().splitlines()
        at = next((i for i, old in enumerate(lines) if old.startswith(f"| `{case}` |")), None)
        if at is None:
            at = max(i for i, old in enumerate(lines) if old.startswith("|")) + 1
            lines.insert(at, line)
        else:
            lines[at] = line
        DOC.write_text("\n".join(lines) + "\n")
        return
    documented = rows().get(case)
    assert documented is not None, f"docs/errors.md has no row for `{case}`; add it with {UPDATE_ENV}=1:\n{line}"
    assert documented == (entry, bad_input, message), (
        f"docs/errors.md is stale for `{case}` (rewrite it with {UPDATE_ENV}=1 and review the diff):\n"
        f"  documented: {documented}\n  produced:   {(entry, bad_input, message)}"
    )
