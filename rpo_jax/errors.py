"""Bad input, reported the same way by every entry point (one line and exit code 2), and Ctrl-C."""

from __future__ import annotations

import sys


class UsageError(ValueError):
    """Bad input from the user or a caller of the library: reported as one line with exit code 2."""


class Interrupted(Exception):
    """Ctrl-C during training; carries the run directory to resume."""


def usage_failure(error: UsageError) -> int:
    """Prints `error` as the one line the user sees and returns the exit code for bad input."""
    print(f"error: {error}", file=sys.stderr)
    return 2
