"""`rpo-jax COMMAND ...` (or `python -m rpo_jax COMMAND ...`): one entry point for every command,
each the same as `python -m rpo_jax.COMMAND ...`."""

from __future__ import annotations

import importlib
import sys
from typing import Sequence

from rpo_jax import __version__

# command -> (module, what it does)
COMMANDS = {
    "train": ("rpo_jax.train", "train PPO, RPO, RAD or DrAC on one environment"),
    "experiment": ("rpo_jax.experiment", "run one of the paper's comparisons"),
    "evaluate": ("rpo_jax.evaluate", "evaluate a trained run's policy"),
    "report": ("rpo_jax.report.compose", "tables, statistics and figures from runs and experiments"),
    "export": ("rpo_jax.export", "a trained policy as ONNX or NumPy arrays"),
    "envs": ("rpo_jax.envs.__main__", "list the environments, or check one"),
}
USAGE = "usage: rpo-jax COMMAND [ARGS...]   (rpo-jax COMMAND --help for a command's flags)\n\ncommands:\n" + "\n".join(
    f"  {name:<11} {about}" for name, (_, about) in COMMANDS.items()
)


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(USAGE)
        return 0
    if argv[0] == "--version":
        print(f"rpo_jax {__version__}")
        return 0
    if argv[0] not in COMMANDS:
        print(f"error: unknown command {argv[0]!r}; commands are {', '.join(COMMANDS)} (rpo-jax --help)", file=sys.stderr)
        return 2
    module = importlib.import_module(COMMANDS[argv[0]][0])
    return module.main(argv[1:])


if __name__ == "__main__":
    sys.exit(main())
