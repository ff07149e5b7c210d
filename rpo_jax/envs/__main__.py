"""`python -m rpo_jax.envs`: one line per registered environment, from the declared specs;
`python -m rpo_jax.envs --check NAME`: the problems `check_env` finds with one, a line each."""

from __future__ import annotations

import sys

from rpo_jax.errors import UsageError, command_failures

USAGE = (
    "usage: python -m rpo_jax.envs [--check NAME]\n\n"
    "Lists every registered environment, one line each: its name (what --env takes), its backend "
    "(mjx, jax, brax-<pipeline> or host), its observation and action sizes, and its episode length "
    "in steps. It reads the static specs and builds no environment, so it needs none of the "
    "optional extras; its last lines say which extras are installed.\n\n"
    "--check NAME builds the environment NAME (a registered name, gymnasium/<id> or an import path "
    "package.module:factory), runs it and prints one line per problem with what the trainer relies on "
    "(rpo_jax.check_env); exit code 1 if it found any, 0 if none."
)
NOTE = (
    "\nAlso: gymnasium/<id>, any Gymnasium task with Box observation and action spaces, on the host "
    "(e.g. gymnasium/HalfCheetah-v5); package.module:factory, an environment of your own."
)


def extras_lines() -> list[str]:
    """One line per optional extra: installed, or the command that installs it. Found without
    importing the modules."""
    from rpo_jax.envs.registry import EXTRAS, missing_modules

    lines = []
    for extra, (prefixes, _) in EXTRAS.items():
        missing = missing_modules(extra)
        state = f"not installed (no {', '.join(missing)}): pip install '.[{extra}]'" if missing else "installed"
        names = ", ".join(prefix + "*" if prefix.endswith("/") else prefix for prefix in prefixes)
        lines.append(f"extra {extra} ({names}): {state}")
    return lines


def list_envs() -> None:
    # Imported here so that --help loads no JAX.
    from rpo_jax.envs.registry import env_names, env_spec

    rows = [("name", "backend", "obs", "act", "episode")]
    for name in env_names():
        spec = env_spec(name)
        rows.append((name, spec.backend, str(spec.observation_size), str(spec.action_size), str(spec.max_episode_steps)))
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    for row in rows:
        print("  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip())
    print(NOTE)
    print()
    print("\n".join(extras_lines()))


def check(name: str) -> int:
    from rpo_jax.envs.check import check_env
    from rpo_jax.envs.registry import make_env

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
    with command_failures() as exit:
        if len(argv) == 2 and argv[0] == "--check":
            return check(argv[1])
        if argv:
            raise UsageError(f"python -m rpo_jax.envs takes no arguments or --check NAME, got {' '.join(argv)} (see --help)")
        list_envs()
    return exit.code


if __name__ == "__main__":
    raise SystemExit(main())
