"""DeepMind Control on MJX (`mjx-dmc/<domain>-<task>`): MuJoCo Playground's ports of the suite,
pure JAX environments that train inside the one jitted program like Cartpole, on GPU or CPU.

Playground ports 25 of the suite's tasks, 9 of the paper's 12 (not quadruped). The names are the
host-side suite's (`dmc/walker-walk` and `mjx-dmc/walker-walk`), and so are the observation
layouts: Playground concatenates the same keys in dm_control's order (tests/test_playground.py
checks the sizes against `dmc_tasks.TASKS`). Its models are tuned for MJX (fewer contacts, some
solver settings), so returns are close to dm_control's but not equal.

MJX runs through its JAX implementation (`impl='jax'`), which works on every JAX backend;
Playground's default, MuJoCo Warp, needs an NVIDIA GPU. Playground's `done` (a diverged
simulation) is a termination; its 1000-step episodes are `wrappers.TimeLimit` truncations.
"""

from __future__ import annotations

import contextlib
import copy
import io
from typing import Any, Callable

import jax

from rpo_jax.envs.dmc_tasks import EPISODE_STEPS, PLAYGROUND_NAMES, TASKS
from rpo_jax.envs.protocol import EnvSpec, MissingExtraError
from rpo_jax.envs.wrappers import DoneIsTermination


def _spec(task: str) -> EnvSpec:
    action_size, keys = TASKS[task]
    ones = (1.0,) * action_size  # every Playground DMC actuator's control range is [-1, 1]
    obs_size = sum(size for _, size in keys)
    return EnvSpec(f"mjx-dmc/{task}", obs_size, action_size, tuple(-x for x in ones), ones, EPISODE_STEPS, "mjx")


SPECS = {f"mjx-dmc/{task}": _spec(task) for task in PLAYGROUND_NAMES}


class PlaygroundEnv(DoneIsTermination):
    """One Playground DMC task behind the protocol. The state is Playground's own `State`."""

    def __init__(self, task: str) -> None:
        try:
            # mujoco.mjx prints a line on stdout when the optional Warp backend is missing.
            with contextlib.redirect_stdout(io.StringIO()):
                from mujoco_playground import dm_control_suite
        except ImportError:
            raise MissingExtraError(f"mjx-dmc/{task}", "mujoco_playground", "playground") from None
        from rpo_jax.envs.mjx_support import models_on_this_process

        self.spec = SPECS[f"mjx-dmc/{task}"]
        with models_on_this_process():
            self.env = dm_control_suite.load(PLAYGROUND_NAMES[task], config_overrides={"impl": "jax"})
        self.mj_model, self.control_dt = self.env.mj_model, float(self.env.dt)

    @property
    def model(self) -> Any:
        """The MJX model Playground's task steps (`protocol.SimulatesModel`)."""
        return self.env.mjx_model

    def with_model(self, change: Callable[[Any], Any]) -> PlaygroundEnv:
        env = copy.copy(self)
        env.env = copy.copy(self.env)
        env.env._mjx_model = change(self.env.mjx_model)  # what Playground's `mjx_model` reads
        return env

    @staticmethod
    def pushed(state: Any, velocity: jax.Array) -> Any:
        return state.replace(data=state.data.replace(qvel=state.data.qvel + velocity))

    @staticmethod
    def qpos(state: Any) -> jax.Array:
        return state.data.qpos
