"""Each entry point's `--help` opens with its purpose and three examples and lists only the options it takes."""

from __future__ import annotations

import subprocess
import sys

import pytest

VERBS = [
    "train",
    "evaluate",
    "render",
    "view",
    "export",
    "prune",
    "survey",
    "report",
    "data.convert",
    "data.check",
    "data.studio",
]
TAKES_GROUPS = {"train", "survey"}  # they compose the training config's groups; the others read a checkpoint


@pytest.mark.parametrize("verb", VERBS)
def test_help_opens_with_purpose_and_examples(verb: str) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", f"framework.{verb}", "--help"], capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = [line for line in proc.stdout.splitlines() if not line.startswith("[splatrig]")]
    assert lines[0].startswith(f"python -m framework.{verb}: "), lines[:3]
    examples = [line for line in lines if line.startswith(f"  python -m framework.{verb} ")]
    assert len(examples) >= 3, lines
    assert "powered by Hydra" not in proc.stdout
    assert ("densifier: " in proc.stdout) == (verb in TAKES_GROUPS)  # a training group only where it is taken
    if verb == "train":
        assert "+experiment=paper_full" in lines[3]
