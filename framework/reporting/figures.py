"""Writing report figures: a PNG written atomically, so an interrupted report never leaves half an image."""

from __future__ import annotations

from pathlib import Path

from framework.atomic import atomic_path


def save_png(fig, path: Path, dpi: int = 120) -> Path:
    """Save a matplotlib figure as `path` (atomically, framework.atomic)."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi)
    return path
