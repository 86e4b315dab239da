"""Shared test setup: the hypothesis profiles of the numerical-extremes properties (few examples by default; set
SPLATRIG_HYPOTHESIS_PROFILE=slow for many, see framework/testing/properties.py), one CPU thread per pytest-xdist
worker, and the tiny trained avatar that several modules share."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest
import torch

import framework.testing.properties  # noqa: F401  (registers and loads the profile)

XDIST_WORKER = os.environ.get("PYTEST_XDIST_WORKER")

# The benchmark tools' helpers (tools/_bench) import by package name, as when a tool runs as a script from tools/.
TOOLS = str(Path(__file__).resolve().parents[1] / "tools")
if TOOLS not in sys.path:
    sys.path.insert(0, TOOLS)

if XDIST_WORKER is not None:
    # The workers already keep every core busy: a second torch thread per worker only oversubscribes them. Tests that
    # need several threads set their count themselves.
    torch.set_num_threads(1)


@pytest.fixture(scope="session")
def tiny_avatar(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(checkpoint, SPLATRIG_CACHE_DIR it needs) of tests/trained_avatar.py's tiny avatar, trained once per test run:
    under pytest-xdist in the folder all workers share (the file lock makes the first one build it)."""
    from trained_avatar import tiny_checkpoint

    base = tmp_path_factory.getbasetemp()
    root = (base.parent if XDIST_WORKER is not None else base) / "tiny_avatar"
    root.mkdir(exist_ok=True)
    return tiny_checkpoint(root)
