"""`python -m rpo_jax.envs`: one line per registered environment, from the declared specs."""

from __future__ import annotations

import importlib.util
import sys

USAGE = (
    "usage: python -m rpo_jax.envs\n\n"
    "Lists every registered environment, one line each: its name (what --env takes), its backend "
    "(mjx, jax, brax-<pipeline> or host), its observation and action sizes, and its episode length "
    "in steps. It reads the static specs and builds no environment, so it needs none of the "
    "optional extras; its last lines say which extras are installed."
)
# The optional extras (pyproject.toml), the names they provide and the modules they install.
EXTRAS = {
    "gym": ("gym/", ("gymnax", "gymnasium", "Box2D")),
    "dmc": ("dmc/", ("envpool",)),
    "pybullet": ("pybullet/", ("pybullet", "pybullet_envs")),
    "playground": ("mjx-dmc/", ("mujoco_playground",)),
}


def extras_lines() -> list[str]:
    """One line per optional extra: installed, or the command that installs it. Found without
    importing the modules."""
    lines = []
    for extra, (prefix, modules) in EXTRAS.items():
        missing = [module for module in modules if importlib.util.find_spec(module) is None]
        state = f"not installed (no {', '.join(missing)}): pip install -e '.[{extra}]'" if missing else "installed"
        lines.append(f"extra {extra} ({prefix}*): {state}")
    return lines


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv in (["--help"], ["-h"]):
        print(USAGE)
        return 0
    if argv:
        print(f"error: python -m rpo_jax.envs takes no arguments, got {' '.join(argv)} (see --help)", file=sys.stderr)
        return 2
    from rpo_jax.envs.registry import env_names, env_spec

    rows = [("name", "backend", "obs", "act", "episode")]
    for name in env_names():
        spec = env_spec(name)
        rows.append((name, spec.backend, str(spec.observation_size), str(spec.action_size), str(spec.max_episode_steps)))
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    for row in rows:
        print("  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip())
    print()
    print("\n".join(extras_lines()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
