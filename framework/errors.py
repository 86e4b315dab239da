"""User-facing errors: the entry points print these as one message (no traceback), exit code 2."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager


class SplatrigError(Exception):
    """Bad input or configuration; the message names the thing, what was expected, what was found, and the fix."""


@contextmanager
def reported_as_message() -> Iterator[None]:
    """Turn a SplatrigError into `error: ...` on stderr and exit 2 (SPLATRIG_FULL_ERROR=1 keeps the traceback)."""
    try:
        yield
    except SplatrigError as exc:
        if os.environ.get("SPLATRIG_FULL_ERROR"):
            raise
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
