"""What the argparse-based command-line tools share: a parser whose errors are one line."""

from __future__ import annotations

import argparse
from typing import Any

from rpo_jax.errors import UsageError


class ArgumentParser(argparse.ArgumentParser):
    def __init__(self, *args: Any, **kwargs: Any) -> None:
        # An abbreviated flag (--num-env for --num-envs) is an error, not a guess.
        super().__init__(*args, allow_abbrev=False, **kwargs)

    def error(self, message: str) -> None:  # argparse's default prints the whole usage too
        raise UsageError(message)
