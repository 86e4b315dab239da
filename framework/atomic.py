"""Files that are complete or absent: nothing we write can be read half-written after an interruption.

`atomic_path(target)` yields a temporary path beside the target (same folder, same suffix, so numpy, OpenCV and
imageio still pick the format from the name); when the block ends without an exception the file is flushed to disk
(fsync), renamed over the target (atomic on POSIX file systems) and the folder entry is synced too. A kill at any
moment leaves the previous file (or none) under the target's name, plus at worst a hidden `.<name>.tmp-<pid><suffix>`
leftover that `remove_stale_temporaries` clears.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

_TMP = ".tmp-"


def temporary_path(path: str | os.PathLike) -> Path:
    """Where `atomic_path` writes `path` first: `.<name>.tmp-<pid><suffix>` in the same folder."""
    path = Path(path)
    return path.with_name(f".{path.name}{_TMP}{os.getpid()}{path.suffix}")


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    except OSError:  # e.g. a folder on a file system that cannot sync folders: the rename is still atomic
        pass
    finally:
        os.close(fd)


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Write to the yielded temporary path; on success it replaces `path` durably, on failure it is removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_path(path)
    try:
        yield tmp
        _fsync(tmp)
        os.replace(tmp, path)
        _fsync(path.parent)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write `text` to `path` atomically (see `atomic_path`); returns the path."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def remove_stale_temporaries(path: str | os.PathLike) -> list[Path]:
    """Remove the temporaries of `path` left by writers that were killed (any process but this one)."""
    path = Path(path)
    mine = temporary_path(path).name
    removed = []
    for leftover in path.parent.glob(f".{path.name}{_TMP}*"):
        if leftover.name != mine:
            leftover.unlink(missing_ok=True)
            removed.append(leftover)
    return removed
