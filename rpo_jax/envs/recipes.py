"""What the suites say of a name before anything is built, for the commands and the run layer,
which ask here rather than of a suite: the presets (the paper's, `rpo_jax.config`, and each
suite's own), the preset a task trains with, and the sensing settings a name takes as options.
Imports no simulator and no JAX, so that `--help` lists the presets at once."""

from __future__ import annotations

from rpo_jax.config import PAPER_PRESETS, Config
from rpo_jax.envs import dmc_tasks, robot_tasks
from rpo_jax.errors import UsageError

PRESETS: dict[str, Config] = {**PAPER_PRESETS, **robot_tasks.PRESETS}
# IsaacGym's tasks, rebuilt on MJX, trained in the paper with rl_games' config for each.
TASK_PRESETS = {"cartpole": "isaacgym", "ballbalance": "isaacgym-ballbalance"}
# The paper's DeepMind Control tasks on the host (envpool), and those MuJoCo Playground ports to
# MJX (all but the quadruped's).
PAPER_DMC = tuple(f"dmc/{task}" for task in dmc_tasks.PAPER_TASKS)
PAPER_MJX_DMC = tuple(f"mjx-dmc/{task}" for task in dmc_tasks.PAPER_TASKS if task in dmc_tasks.PLAYGROUND_NAMES)


def preset_for(name: str) -> str | None:
    """The preset that the task `name` was tuned with (whatever the options of its name); None
    where it has none of its own."""
    return TASK_PRESETS.get(name) or robot_tasks.preset_of(name)


def preset_mismatch(preset: str, name: str) -> str | None:
    """Why `preset`, made for other tasks, does not fit what `name` trains; None where it fits or
    is no task's own."""
    return robot_tasks.preset_mismatch(preset, name)


def with_sensing(name: str, obs_noise: float | None, push: bool | None) -> str:
    """`name` with its sensors' noise scale (0: none) and its pushes (on or off) among its
    options, where given (None: the task's own); UsageError for a task without such settings."""
    given = {robot_tasks.NOISE_LEVEL: obs_noise, robot_tasks.PUSH_ENABLE: push}
    options = {key: value for key, value in given.items() if value is not None}
    if not options:
        return name
    if not name.startswith((robot_tasks.PREFIX, robot_tasks.MJX_PREFIX)):
        raise UsageError(f"--obs-noise and --push apply to robot/ and mjx-robot/ tasks, not {name!r}")
    if obs_noise is not None and not obs_noise >= 0:
        raise UsageError(f"--obs-noise must be >= 0 (0: no noise, 1: the task's own scale), got {obs_noise}")
    return robot_tasks.with_options(name, options)
