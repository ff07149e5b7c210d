"""The environment protocol: what every environment and wrapper in `rpo_jax.envs` implements.

The protocol (`Env`) is two pure functions and a spec:

    state, ts = env.reset(key)
    state, ts = env.step(state, action)

`ts` is a `TimeStep`: the observation to act on next, the reward, separate termination and
truncation flags, and `final_obs`, the observation the step actually reached. After an
auto-reset, `obs` is the first observation of the new episode while `final_obs` keeps the
last one of the old episode, so a truncated episode can still be bootstrapped.

A single JAX environment (Cartpole on MJX, a Brax environment) returns unbatched arrays; a
`BatchedEnv` gives the same protocol with a leading batch axis of `num_envs`. Host-side
environments (`Vectorizable`) exist only batched and build their batch themselves.

This module imports jax and flax only, no simulator.
"""

from __future__ import annotations

import copy
import dataclasses
from typing import TYPE_CHECKING, Any, Callable, Protocol, runtime_checkable

import jax
import jax.numpy as jnp
from flax import struct

from rpo_jax.errors import UsageError

if TYPE_CHECKING:
    import mujoco


@dataclasses.dataclass(frozen=True)
class EnvSpec:
    """Static facts of an environment.

    An observation of named parts (a robot's `state` for the policy and `privileged_state` for
    the critic) is their concatenation in `observation_keys`' order; `policy_obs_key` and
    `critic_obs_key` name the part each network reads ("" for the whole observation). Being
    elementwise, the observation normaliser normalises each part on its own."""

    name: str
    observation_size: int
    action_size: int
    action_low: tuple[float, ...]
    action_high: tuple[float, ...]
    max_episode_steps: int
    backend: str
    observation_keys: tuple[tuple[str, int], ...] = ()  # ((name, size), ...); () for one unnamed array
    policy_obs_key: str = ""
    critic_obs_key: str = ""

    def __post_init__(self) -> None:
        names = [name for name, _ in self.observation_keys]
        for name, size in self.observation_keys:
            if not isinstance(name, str) or not name:
                raise ValueError(f"{self.name}: an observation part is named by a non-empty string, got {name!r}")
            if isinstance(size, bool) or not isinstance(size, int) or size <= 0:
                raise ValueError(f"{self.name}: observation part {name!r} must have a positive integer size, got {size!r}")
        if len(set(names)) < len(names):
            raise ValueError(f"{self.name}: observation_keys name a part twice: {names}")
        if self.observation_keys and sum(size for _, size in self.observation_keys) != self.observation_size:
            raise ValueError(f"{self.name}: observation_keys' sizes must add up to observation_size")
        for key in (self.policy_obs_key, self.critic_obs_key):
            if key and key not in dict(self.observation_keys):
                raise ValueError(f"{self.name}: {key!r} is not one of observation_keys {self.observation_keys}")

    def part(self, key: str) -> tuple[int, int] | None:
        """[start, stop) of the observation's part `key`; None for "" (the whole observation)."""
        if not key:
            return None
        start = 0
        for name, size in self.observation_keys:
            if name == key:
                return start, start + size
            start += size
        raise KeyError(key)

    @property
    def policy_observation_size(self) -> int:
        """The numbers the policy reads: what an exported policy takes."""
        part = self.part(self.policy_obs_key)
        return self.observation_size if part is None else part[1] - part[0]

    def record(self) -> dict[str, Any]:
        """The spec as config.json records it: the named observations' fields only where it has
        them, so that a flat task's record is what it was before they existed."""
        record = dataclasses.asdict(self)
        if not self.observation_keys:
            for key in ("observation_keys", "policy_obs_key", "critic_obs_key"):
                del record[key]
        return record

    @classmethod
    def from_record(cls, record: dict[str, Any]) -> "EnvSpec":
        """The spec that config.json records (`dataclasses.asdict`; runs written before named
        observations lack their fields)."""
        lists = ("action_low", "action_high")
        fields = {key: tuple(value) if key in lists else value for key, value in record.items()}
        fields["observation_keys"] = tuple((name, size) for name, size in record.get("observation_keys", ()))
        return cls(**fields)

    @property
    def runs_on_host(self) -> bool:
        """Whether the simulator runs on the host, outside JAX (so no checkpoint holds its state)."""
        return self.backend == "host"


@struct.dataclass
class TimeStep:
    """What reset and step return. Shapes are [] / [obs] for one environment, [N] / [N, obs] batched."""

    obs: jax.Array
    reward: jax.Array
    terminated: jax.Array
    truncated: jax.Array
    final_obs: jax.Array
    info: dict[str, jax.Array] = struct.field(default_factory=dict)


class Env(Protocol):
    """What the trainer drives. The batch wrappers also define `restart(state, key)`: fresh
    episodes that keep the statistics in `state` (plain `reset` for those that keep none),
    which a resumed host run calls when it starts its simulators again."""

    spec: EnvSpec

    def reset(self, key: jax.Array) -> tuple[Any, TimeStep]:
        """A new episode drawn from `key` (a PRNG key): the state (a pytree) and its first
        `TimeStep` (obs [obs_size], or [N, obs_size] batched)."""
        ...

    def step(self, state: Any, action: jax.Array) -> tuple[Any, TimeStep]:
        """One step with `action` [action_size] ([N, action_size] batched): the next state and
        its `TimeStep`."""
        ...


@runtime_checkable
class BatchedEnv(Env, Protocol):
    """An environment whose arrays carry a leading batch axis of `num_envs`."""

    num_envs: int


@struct.dataclass
class Start:
    """What `draw_starts` returns besides the state: whether the environments started at this
    draw (the first one after a deferred reset) and, where they did, their first observations."""

    started: jax.Array  # [] bool
    obs: jax.Array  # [N, obs_size]


@runtime_checkable
class DrawsStarts(Protocol):
    """A batched environment that restarts its episodes from a pool of initial states drawn
    ahead (`wrappers.VectorEnv`): `draw_starts(state, key) -> (state, Start)` draws a new
    pool, which the trainer asks for once before each rollout. The batch wrappers pass it down.

    With `defers_start`, `reset` only lays out the state, its observations are placeholders,
    and the environments start at the first draw, from its pool: so a program that resets
    and trains holds one copy of the environment's reset, the pool's, not two."""

    defers_start: bool

    def draw_starts(self, state: Any, key: jax.Array) -> tuple[Any, Start]:
        """A new pool of initial states drawn from `key`, for the episodes that end in the next rollout."""
        ...


@runtime_checkable
class Vectorizable(Protocol):
    """An environment that builds its own batch (the host-side ones): `vectorize(num_envs)`
    gives the batched environment the trainer steps."""

    spec: EnvSpec

    def vectorize(self, num_envs: int) -> BatchedEnv:
        """The batched environment of `num_envs` simulators."""
        ...


@runtime_checkable
class Renderable(Protocol):
    """What a MuJoCo-based environment adds so that videos (`rpo_jax.evaluate --video`, `train
    --capture-video`) can draw it: its model, and the joint positions of a state. An environment
    may also have a `render_model`, a copy of `mj_model` with the same joints dressed for
    pictures (light, floor, colours), which videos draw instead."""

    mj_model: mujoco.MjModel
    control_dt: float  # seconds per step, for the video's frame rate

    def qpos(self, state: Any) -> jax.Array:
        """MuJoCo's joint positions [mj_model.nq] of one environment's state, to render it."""
        ...


def first_step(obs: jax.Array) -> TimeStep:
    """The time step of a reset: `obs` [..., obs_size], no reward, no episode ended."""
    false = jnp.zeros(obs.shape[:-1], bool)
    return TimeStep(obs, jnp.zeros(obs.shape[:-1]), false, false, obs)


class MissingExtraError(UsageError):
    """An environment needs an optional dependency that is not installed."""

    def __init__(self, name: str, module: str, extra: str) -> None:
        super().__init__(f"env {name!r} needs {module}, which is not installed: pip install '.[{extra}]'")


@runtime_checkable
class SimulatesModel(Protocol):
    """An environment that steps an MJX model inside the program, which `perturbations` changes:
    `model` is the nominal one; `with_model(change)` a copy of the environment that steps
    `change(model)` wherever it would step `model` (the original untouched)."""

    @property
    def model(self) -> Any:
        """The nominal MJX model."""
        ...

    def with_model(self, change: Callable[[Any], Any]) -> Env:
        """A copy stepping `change(model)` wherever this one steps `model`."""
        ...

    def pushed(self, state: Any, velocity: jax.Array) -> Any:
        """`state` with `velocity` [nv] added to its joint velocities."""
        ...


class StepsOwnModel:
    """`SimulatesModel` for an environment whose steps read its `model` attribute and whose state
    carries its joint velocities as `qvel` (Cartpole's, BallBalance's)."""

    model: Any

    def with_model(self, change: Callable[[Any], Any]) -> Env:
        """A shallow copy whose `model` is `change(model)`."""
        env = copy.copy(self)
        env.model = change(self.model)
        return env

    def pushed(self, state: Any, velocity: jax.Array) -> Any:
        """`state` with `velocity` added to its `qvel`."""
        return state.replace(qvel=state.qvel + velocity)
