"""User-facing errors: the entry points print these as one message (no traceback), exit code 2."""


class SplatrigError(Exception):
    """Bad input or configuration; the message names the thing, what was expected, what was found, and the fix."""
