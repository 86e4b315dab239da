"""Writing report figures: a PNG written atomically, so an interrupted report never leaves half an image."""

from __future__ import annotations

import os
from pathlib import Path


def save_png(fig, path: Path, dpi: int = 120) -> Path:
    """Save a matplotlib figure as `path` (through a temporary file and os.replace)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp.png")
    fig.savefig(tmp, dpi=dpi)
    os.replace(tmp, path)
    return path
