"""What the command-line tools share: one-line usage errors and files written whole or not at all."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any


class UsageError(Exception):
    """Bad input from the user: reported as one line with exit code 2."""


def usage_failure(error: UsageError) -> int:
    """Prints `error` as the one line the user sees and returns the exit code for bad input."""
    print(f"error: {error}", file=sys.stderr)
    return 2


class ArgumentParser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # argparse's default prints the whole usage too
        raise UsageError(message)


def write_text(path: Path, text: str) -> None:
    """Writes through a temporary file and a rename, so a crash never leaves half a file."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def write_json(path: Path, payload: Any) -> None:
    write_text(path, json.dumps(payload, indent=2) + "\n")
