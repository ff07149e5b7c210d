"""Any Gymnasium task whose observation and action spaces are 1-D Boxes, stepped on the host:
`gymnasium/<id>`, for example `gymnasium/HalfCheetah-v5` (Gymnasium's MuJoCo tasks run on the
installed MuJoCo) or `gymnasium/LunarLanderContinuous-v3` (Box2D, the `gym` extra).

Each simulator is `gymnasium.make(id)` with Gymnasium's default wrappers, so the task's own
time limit (`max_episode_steps` of its registration) ends episodes as truncations, and the spec
is read from the spaces of one instance. A task without a time limit, or with another kind of
space (Discrete, Dict, images), is refused with a one-line error.
"""

from __future__ import annotations

import re
from typing import Any, Callable

import numpy as np

from rpo_jax.envs import perturbations
from rpo_jax.envs.host import HostEnv, SequentialSimulators
from rpo_jax.envs.protocol import EnvSpec, MissingExtraError
from rpo_jax.errors import UsageError

PREFIX = "gymnasium/"


def _import_gymnasium(name: str) -> Any:
    try:
        import gymnasium
    except ImportError:
        raise MissingExtraError(name, "gymnasium", "gym") from None
    return gymnasium


def _make_one(gym_id: str, name: str, **kwargs: Any) -> Any:
    gymnasium = _import_gymnasium(name)
    try:
        return gymnasium.make(gym_id, **kwargs)
    except gymnasium.error.Error as error:
        # Unknown ids and versions, and missing dependencies (Box2D), whose messages say what to install.
        message = re.sub(r"\s+", " ", str(error)).strip()
        raise UsageError(f"env {name!r}: {message}") from None


def _check_box(name: str, role: str, space: Any) -> None:
    from gymnasium import spaces

    if not isinstance(space, spaces.Box) or len(space.shape) != 1:
        raise UsageError(
            f"env {name!r}: its {role} space is {space}; rpo_jax takes Gymnasium tasks whose observation "
            "and action spaces are 1-D Boxes (continuous control)"
        )


def read_spec(name: str, env: Any) -> EnvSpec:
    """The spec of the Gymnasium environment `env`, registered as `name`."""
    _check_box(name, "observation", env.observation_space)
    _check_box(name, "action", env.action_space)
    steps = env.spec.max_episode_steps if env.spec is not None else None
    if steps is None:
        raise UsageError(f"env {name!r} has no time limit (max_episode_steps in its Gymnasium registration); rpo_jax needs one")
    low, high = env.action_space.low, env.action_space.high
    return EnvSpec(
        name, env.observation_space.shape[0], env.action_space.shape[0],
        tuple(float(x) for x in low), tuple(float(x) for x in high), int(steps), "host",
    )  # fmt: skip


def _seeded(gym_id: str, name: str, index: int, seed: int) -> Any:
    env = _make_one(gym_id, name)
    env.reset(seed=int(np.random.SeedSequence([seed, index]).generate_state(1)[0]))
    return env


def _reset(env: Any) -> np.ndarray:
    return env.reset()[0]


def _step(env: Any, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool]:
    obs, reward, terminated, truncated, _ = env.step(action)
    return obs, reward, terminated, truncated


def _close(env: Any) -> None:
    env.close()


class DrawnTask:
    """One Gymnasium task that draws itself (`render_mode="rgb_array"`, at its own size and
    frame rate): `host.DrawnSimulator`."""

    def __init__(self, gym_id: str, name: str, seed: int) -> None:
        self.env = _make_one(gym_id, name, render_mode="rgb_array")
        self.seed = seed
        self.fps = float(self.env.metadata.get("render_fps") or 30)

    def reset(self) -> np.ndarray:
        obs = self.env.reset(seed=self.seed)[0]
        self.seed += 1  # the next episode starts elsewhere
        return obs

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool]:
        return _step(self.env, action)

    def frame(self) -> np.ndarray:
        return np.asarray(self.env.render())

    def close(self) -> None:
        self.env.close()


def serves(name: str) -> bool:
    """Whether `name` is one of this suite's unlisted names: `gymnasium/<id>`, any Gymnasium task."""
    return name.startswith(PREFIX)


def unlisted(name: str, import_function: Any) -> tuple[Callable[[], HostEnv], EnvSpec | None]:
    """The factory of `name`, one that `serves`, and its spec where known without building it
    (Gymnasium's is read from a built task: None)."""
    return (lambda: make(name.removeprefix(PREFIX))), None


def make(gym_id: str, name: str | None = None) -> HostEnv:
    """Gymnasium's task `gym_id` behind the host path, named `name` (default gymnasium/<id>).
    Simulator i of a pool seeded `seed` is seeded from (seed, i)."""
    name = name or PREFIX + gym_id
    probe = _make_one(gym_id, name)
    try:
        spec = read_spec(name, probe)
    finally:
        probe.close()

    def make_simulators(num_envs: int, seed: int) -> SequentialSimulators:
        make_seeded = lambda index, seed: _seeded(gym_id, name, index, seed)
        return SequentialSimulators(num_envs, seed, make_seeded, _reset, _step, _close)

    def with_physics(factors: dict[str, float]) -> HostEnv:
        probe = _make_one(gym_id, name)
        try:
            model = getattr(probe.unwrapped, "model", None)
            if type(model).__name__ != "MjModel":
                raise UsageError(
                    f"{name} is not one of Gymnasium's MuJoCo tasks, so {next(iter(factors))} cannot change; "
                    f"its axes are {', '.join(perturbations.SIGNAL_AXES)}"
                )
            perturbations.check_model(name, model, tuple(factors))
        finally:
            probe.close()

        def make_scaled(num_envs: int, seed: int) -> SequentialSimulators:
            pool = make_simulators(num_envs, seed)
            for sim in pool.sims:
                for axis, factor in factors.items():
                    perturbations.scale_in_place(sim.unwrapped.model, axis, factor)
            return pool

        return HostEnv(spec, make_scaled)

    drawn = lambda seed, width, height: DrawnTask(gym_id, name, seed)  # noqa: E731
    return HostEnv(spec, make_simulators, drawn, with_physics=with_physics)
