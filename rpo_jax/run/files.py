"""Files written whole or not at all."""

from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path
from typing import Any, Iterator


@contextlib.contextmanager
def written_whole(path: Path, suffix: str = ".tmp") -> Iterator[Path]:
    """A temporary file beside `path` (its name + `suffix`) for the block to write, renamed to
    `path` when the block ends, removed when it fails: a crash never leaves half a file."""
    tmp = path.with_name(path.name + suffix)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)  # a full disk's half-written file: its space back, nothing left to mistake
        raise


def write_bytes(path: Path, data: bytes) -> None:
    """Writes through a temporary file and a rename (`written_whole`)."""
    with written_whole(path) as tmp:
        tmp.write_bytes(data)


def write_text(path: Path, text: str) -> None:
    write_bytes(path, text.encode())


def write_json(path: Path, payload: Any) -> None:
    # allow_nan=False: NaN and Infinity are not JSON, and a reader of the file would choke on them.
    write_text(path, json.dumps(payload, indent=2, allow_nan=False) + "\n")
