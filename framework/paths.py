"""Where generated assets and data live: one cache root, overridable for CI and clusters."""

from __future__ import annotations

import os
from pathlib import Path


def cache_dir() -> Path:
    """`$SPLATRIG_CACHE_DIR`, else `~/.cache/splatrig`; created on first use."""
    root = Path(os.environ.get("SPLATRIG_CACHE_DIR", Path.home() / ".cache" / "splatrig")).expanduser()
    root.mkdir(parents=True, exist_ok=True)
    return root


def data_dir() -> Path:
    """Generated datasets (the synthetic studio, static scenes)."""
    path = cache_dir() / "data"
    path.mkdir(parents=True, exist_ok=True)
    return path
