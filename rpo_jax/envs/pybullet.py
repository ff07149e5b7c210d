"""PyBullet's tasks of the paper, AntBulletEnv-v0 (`pybullet/Ant`) and MinitaurBulletEnv-v0
(`pybullet/Minitaur`), from the `pybullet` package's own `pybullet_envs`, stepped on the host.

`pybullet_envs` is written against the old `gym` package and registers its tasks through
gym's pre-0.24 registry, so the extra pins gym 0.23.1; the tasks are built with `gym.make`
(their registered 1000-step time limit included) and adapted to the protocol here: gym's
`done` is a termination unless its TimeLimit set `info["TimeLimit.truncated"]`.
"""

from __future__ import annotations

import contextlib
import io
import sys
from typing import Any, Iterator

import numpy as np

from rpo_jax.envs.host import HostEnv, SequentialSimulators
from rpo_jax.envs.protocol import EnvSpec, MissingExtraError

GYM_IDS = {"Ant": "AntBulletEnv-v0", "Minitaur": "MinitaurBulletEnv-v0"}
SPECS = {f"pybullet/{name}": EnvSpec(f"pybullet/{name}", 28, 8, (-1.0,) * 8, (1.0,) * 8, 1000, "host") for name in GYM_IDS}


@contextlib.contextmanager
def _sys_path_kept() -> Iterator[None]:
    """pybullet_envs' modules put their own directory first on sys.path when imported, and its
    `examples` package would then hide any other top-level `examples` (a user's environments)."""
    saved = list(sys.path)
    try:
        yield
    finally:
        sys.path[:] = saved


def _import_pybullet_envs() -> Any:
    # pybullet prints its build time and Minitaur its asset paths to stdout; gym warns on
    # stderr that it is unmaintained. Neither belongs in the trainer's output.
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()), _sys_path_kept():
        import gym
        import pybullet_envs  # noqa: F401  (registers the tasks with gym)
    return gym


def _make_one(gym_id: str, index: int, seed: int) -> Any:
    gym = _import_pybullet_envs()
    with contextlib.redirect_stdout(io.StringIO()), _sys_path_kept():
        env = gym.make(gym_id)
    env.seed(int(np.random.SeedSequence([seed, index]).generate_state(1)[0]))
    return env


def _reset(env: Any) -> np.ndarray:
    return np.asarray(env.reset())


def _step(env: Any, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool]:
    obs, reward, done, info = env.step(action)
    truncated = bool(info.get("TimeLimit.truncated", False))
    return np.asarray(obs), reward, done and not truncated, truncated


def _close(env: Any) -> None:
    env.close()


def make(name: str) -> HostEnv:
    try:
        _import_pybullet_envs()
    except ImportError as error:
        raise MissingExtraError(f"pybullet/{name}", error.name or "pybullet", "pybullet") from None
    gym_id = GYM_IDS[name]
    return HostEnv(
        SPECS[f"pybullet/{name}"],
        lambda num_envs, seed: SequentialSimulators(
            num_envs, seed, lambda index, seed: _make_one(gym_id, index, seed), _reset, _step, _close
        ),
    )
