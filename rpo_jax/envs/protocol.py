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

import dataclasses
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import jax
import jax.numpy as jnp
from flax import struct

from rpo_jax.errors import UsageError

if TYPE_CHECKING:
    import mujoco


@dataclasses.dataclass(frozen=True)
class EnvSpec:
    """Static facts of an environment."""

    name: str
    observation_size: int
    action_size: int
    action_low: tuple[float, ...]
    action_high: tuple[float, ...]
    max_episode_steps: int
    backend: str

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
