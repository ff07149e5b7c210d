"""`python -m rpo_jax.envs`: one line per registered environment, from the declared specs;
`python -m rpo_jax.envs --check NAME`: the problems `check_env` finds with one, a line each."""

from __future__ import annotations

import sys

from rpo_jax.envs.check import check_env
from rpo_jax.envs.registry import env_names, env_spec, make_env
from rpo_jax.errors import UsageError, usage_failure

USAGE = (
    "usage: python -m rpo_jax.envs [--check NAME]\n\n"
    "Lists every registered environment, one line each: its name (what --env takes), its backend "
    "(mjx, jax, brax-<pipeline> or host), its observation and action sizes, and its episode length "
    "in steps. It reads the static specs and builds no environment, so it needs none of the "
    "optional extras.\n\n"
    "--check NAME builds the environment NAME (a registered name, gymnasium/<id> or an import path "
    "package.module:factory), runs it and prints one line per problem with what the trainer relies on "
    "(rpo_jax.check_env); exit code 1 if it found any, 0 if none."
)
NOTE = (
    "\nAlso: gymnasium/<id>, any Gymnasium task with Box observation and action spaces, on the host "
    "(e.g. gymnasium/HalfCheetah-v5); package.module:factory, an environment of your own."
)


def list_envs() -> None:
    rows = [("name", "backend", "obs", "act", "episode")]
    for name in env_names():
        spec = env_spec(name)
        rows.append((name, spec.backend, str(spec.observation_size), str(spec.action_size), str(spec.max_episode_steps)))
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    for row in rows:
        print("  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip())
    print(NOTE)


def check(name: str) -> int:
    problems = check_env(make_env(name))
    for problem in problems:
        print(f"{name}: {problem}")
    if not problems:
        print(f"{name}: no problems found")
    return 1 if problems else 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv in (["--help"], ["-h"]):
        print(USAGE)
        return 0
    try:
        if len(argv) == 2 and argv[0] == "--check":
            return check(argv[1])
        if argv:
            raise UsageError(f"python -m rpo_jax.envs takes no arguments or --check NAME, got {' '.join(argv)} (see --help)")
    except UsageError as error:
        return usage_failure(error)
    list_envs()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
