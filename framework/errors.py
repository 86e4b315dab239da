"""User-facing errors: the entry points print these as one message (no traceback), exit code 2."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager


class SplatrigError(Exception):
    """Bad input or configuration; the message names the thing, what was expected, what was found, and the fix."""


def _as_splatrig_error(exc: BaseException) -> SplatrigError | None:
    """The user-facing form of an exception, or None for a bug (which keeps its traceback)."""
    if isinstance(exc, SplatrigError):
        return exc
    from omegaconf.errors import MissingMandatoryValue

    if isinstance(exc, MissingMandatoryValue):  # a `???` in a YAML file that the command line did not fill
        key = getattr(exc, "full_key", None) or "?"
        return SplatrigError(
            f"config key {key}: expected a value, found none ('???' in its config file). Set it on "
            f"the command line, e.g. {key}=<value>."
        )
    return None


@contextmanager
def reported_as_message() -> Iterator[None]:
    """Turn a SplatrigError (or a config value left at `???`) into one `error: ...` line on stderr and exit 2;
    SPLATRIG_FULL_ERROR=1 keeps the traceback."""
    try:
        yield
    except Exception as exc:
        error = _as_splatrig_error(exc)
        if error is None or os.environ.get("SPLATRIG_FULL_ERROR"):
            raise
        print(f"error: {error}", file=sys.stderr)
        sys.exit(2)
