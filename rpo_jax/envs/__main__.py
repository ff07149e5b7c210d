"""`python -m rpo_jax.envs`: one line per registered environment, from the declared specs."""

from __future__ import annotations

import sys

from rpo_jax.envs.registry import env_names, env_spec

USAGE = (
    "usage: python -m rpo_jax.envs\n\n"
    "Lists every registered environment, one line each: its name (what --env takes), its backend "
    "(mjx, jax, brax-<pipeline> or host), its observation and action sizes, and its episode length "
    "in steps. It reads the static specs and builds no environment, so it needs none of the "
    "optional extras."
)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv in (["--help"], ["-h"]):
        print(USAGE)
        return 0
    if argv:
        print(f"error: python -m rpo_jax.envs takes no arguments, got {' '.join(argv)} (see --help)", file=sys.stderr)
        return 2
    rows = [("name", "backend", "obs", "act", "episode")]
    for name in env_names():
        spec = env_spec(name)
        rows.append((name, spec.backend, str(spec.observation_size), str(spec.action_size), str(spec.max_episode_steps)))
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    for row in rows:
        print("  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
