"""Bad input, reported the same way by every entry point (one line and exit code 2), and Ctrl-C."""

from __future__ import annotations

import sys


class UsageError(ValueError):
    """Bad input from the user or a caller of the library: reported as one line with exit code 2."""


class Diverged(Exception):
    """Training met a non-finite number (NaN or inf): the run stopped before it was written or
    checkpointed. Reported as one line with exit code 1: a diverged run is a failed run."""


class Interrupted(Exception):
    """Ctrl-C during training; carries the run directory to resume."""


def usage_failure(error: UsageError) -> int:
    """Prints `error` as the one line the user sees and returns the exit code for bad input."""
    print(f"error: {error}", file=sys.stderr)
    return 2


def os_failure(error: OSError) -> int:
    """Prints a failure of the file system (full disk, read-only, permissions) as one line and
    returns the exit code for bad input: the fix is the user's (another --out, free space)."""
    where = f": {error.filename}" if error.filename else ""
    print(f"error: {error.strerror or error}{where}", file=sys.stderr)
    return 2


def diverged_failure(error: Diverged) -> int:
    print(f"error: {error}", file=sys.stderr)
    return 1
