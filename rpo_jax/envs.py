"""Environments behind one protocol, and the wrappers that training puts around them.

The protocol (`Env`) is two pure functions and a spec:

    state, ts = env.reset(key)
    state, ts = env.step(state, action)

`ts` is a `TimeStep`: the observation to act on next, the reward, separate termination and
truncation flags, and `final_obs`, the observation the step actually reached. After an
auto-reset, `obs` is the first observation of the new episode while `final_obs` keeps the
last one of the old episode, so a truncated episode can still be bootstrapped.

A single JAX environment (Cartpole on MJX, a Brax environment) returns unbatched arrays;
`VectorEnv` vmaps it over `num_envs` copies and gives the same protocol with a leading batch
axis. The batch wrappers (episode statistics, action clipping, reward and observation
normalisation) work on that batched protocol, so a host-side simulator that implements it
directly can sit under them too (`rpo_jax.host`; `vectorize` batches either kind). The trainer
sees only the outermost `Env`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib
import io
import os
import sys
from typing import Any, Callable, Protocol

import jax
import jax.numpy as jnp

# MuJoCo fixes its OpenGL backend at import. Without a display only an offscreen one can work,
# so pick EGL there unless the user chose (rendering is only used by `rpo_jax.evaluate --video`).
if not os.environ.get("DISPLAY"):
    os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np
from flax import struct

from rpo_jax import dmc_tasks

# mujoco.mjx prints (not logs) a line when its optional warp backend is missing; keep stdout clean.
with contextlib.redirect_stdout(io.StringIO()):
    from mujoco import mjx


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
    """What the trainer drives. A wrapper that keeps statistics across episodes (the normalisers)
    also defines `restart(state, key)`: fresh episodes that keep those statistics, which
    `envs.restart` calls when a resumed host run starts its simulators again."""

    spec: EnvSpec

    def reset(self, key: jax.Array) -> tuple[Any, TimeStep]: ...

    def step(self, state: Any, action: jax.Array) -> tuple[Any, TimeStep]: ...


class Renderable(Protocol):
    """What a MuJoCo-based environment adds so that `rpo_jax.evaluate --video` can draw it."""

    mj_model: mujoco.MjModel
    control_dt: float  # seconds per step, for the video's frame rate

    def qpos(self, state: Any) -> jax.Array: ...


def _first_step(obs: jax.Array) -> TimeStep:
    false = jnp.zeros(obs.shape[:-1], bool)
    return TimeStep(obs, jnp.zeros(obs.shape[:-1]), false, false, obs)


# --------------------------------------------------------------------------------------------
# Cartpole (IsaacGym's task on MJX)

CARTPOLE_XML = """
<mujoco model="isaacgym_cartpole">
  <!-- 60 Hz control with 2 substeps. Contacts are off (nothing touches), and so is the
       constraint solver: the rail limit of +-4 m can never bind because the episode ends at
       |x| > 3 m and covering 1 m in one 1/60 s step would take 60 m/s. -->
  <option timestep="0.008333333333333333" gravity="0 0 -9.81" integrator="Euler">
    <flag contact="disable" constraint="disable"/>
  </option>
  <worldbody>
    <geom name="rail" type="box" size="4 0.02 0.02" contype="0" conaffinity="0"/>
    <body name="cart">
      <joint name="slider" type="slide" axis="1 0 0" limited="true" range="-4 4"/>
      <geom name="cart" type="box" size="0.1 0.125 0.1" mass="1" contype="0" conaffinity="0"/>
      <body name="pole" pos="0 0.12 0">
        <joint name="hinge" type="hinge" axis="0 1 0"/>
        <geom name="pole" type="box" size="0.02 0.03 0.5" pos="0 0 0.47" mass="1"
              contype="0" conaffinity="0"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="push" joint="slider" gear="400" ctrllimited="true" ctrlrange="-1 1"/>
  </actuator>
</mujoco>
"""


@struct.dataclass
class CartpoleState:
    qpos: jax.Array  # [2] cart position, pole angle
    qvel: jax.Array  # [2] cart velocity, pole angular velocity


class Cartpole:
    """IsaacGym's Cartpole rebuilt as an MJX model.

    Observation (4): cart position, cart velocity, pole angle, pole angular velocity, clipped
    to +-5. Action (1) in [-1, 1], times 400 N on the cart (the motor's gear). Reward per step
    1 - angle^2 - 0.01 |cart velocity| - 0.005 |pole angular velocity|; when |cart position| > 3
    or |pole angle| > pi/2 that step's reward is -2 and the episode terminates. Episodes are
    truncated after 500 steps by `TimeLimit`. Resets draw both joint positions from U(-0.1, 0.1)
    and both velocities from U(-0.25, 0.25).

    Differences from PhysX: the pole's inertia follows from its box geometry and mass; the
    rail limit is declared but, with MuJoCo's constraint solver off, not enforced (it can never
    bind before termination, see the model). Only qpos and qvel are carried between steps:
    with no contacts and no constraints the rest of mjx.Data is recomputed by every step.
    """

    substeps = 2
    reset_position_range = 0.1
    reset_velocity_range = 0.25
    spec = EnvSpec("cartpole", 4, 1, (-1.0,), (1.0,), 500, "mjx")

    def __init__(self) -> None:
        self.mj_model = mujoco.MjModel.from_xml_string(CARTPOLE_XML)
        self.model = mjx.put_model(self.mj_model)
        self.data_template = mjx.make_data(self.mj_model)
        self.control_dt = self.substeps * float(self.mj_model.opt.timestep)

    @staticmethod
    def qpos(state: CartpoleState) -> jax.Array:
        return state.qpos

    def reset(self, key: jax.Array) -> tuple[CartpoleState, TimeStep]:
        kq, kv = jax.random.split(key)
        p, v = self.reset_position_range, self.reset_velocity_range
        state = CartpoleState(
            qpos=jax.random.uniform(kq, (2,), minval=-p, maxval=p),
            qvel=jax.random.uniform(kv, (2,), minval=-v, maxval=v),
        )
        return state, _first_step(self._observe(state))

    def step(self, state: CartpoleState, action: jax.Array) -> tuple[CartpoleState, TimeStep]:
        data = self.data_template.replace(
            qpos=state.qpos, qvel=state.qvel, ctrl=jnp.clip(action, -1.0, 1.0)
        )
        for _ in range(self.substeps):
            data = mjx.step(self.model, data)
        state = CartpoleState(qpos=data.qpos, qvel=data.qvel)
        x, angle = state.qpos
        x_dot, angle_dot = state.qvel
        terminated = (jnp.abs(x) > 3.0) | (jnp.abs(angle) > jnp.pi / 2)
        reward = 1.0 - angle**2 - 0.01 * jnp.abs(x_dot) - 0.005 * jnp.abs(angle_dot)
        reward = jnp.where(terminated, -2.0, reward)
        obs = self._observe(state)
        return state, TimeStep(obs, reward, terminated, jnp.zeros((), bool), obs)

    @staticmethod
    def _observe(state: CartpoleState) -> jax.Array:
        x, angle = state.qpos
        x_dot, angle_dot = state.qvel
        return jnp.clip(jnp.stack([x, x_dot, angle, angle_dot]), -5.0, 5.0)


# --------------------------------------------------------------------------------------------
# Brax and MuJoCo Playground environments


class DoneIsTermination:
    """Adapts `self.env`, whose `reset(key)` and `step(state, action)` return a state with `obs`,
    `reward` and `done` (Brax's and MuJoCo Playground's environments), to the protocol: `done`
    is a termination, and the time limit is left to `TimeLimit`."""

    env: Any

    def reset(self, key: jax.Array) -> tuple[Any, TimeStep]:
        state = self.env.reset(key)
        return state, _first_step(state.obs)

    def step(self, state: Any, action: jax.Array) -> tuple[Any, TimeStep]:
        state = self.env.step(state, action)
        terminated = state.done.astype(bool)
        return state, TimeStep(state.obs, state.reward, terminated, jnp.zeros((), bool), state.obs)


class BraxEnv(DoneIsTermination):
    """One of Brax's own environments (`brax/<name>`), with Brax's usual 1000-step episodes."""

    def __init__(self, name: str, backend: str | None = None) -> None:
        from brax import envs as brax_envs

        kwargs = {"backend": backend} if backend else {}
        self.env = brax_envs.get_environment(name, **kwargs)
        high = (1.0,) * self.env.action_size
        self.spec = EnvSpec(
            f"brax/{name}",
            int(self.env.observation_size),
            int(self.env.action_size),
            tuple(-h for h in high),
            high,
            1000,
            f"brax-{getattr(self.env, 'backend', backend or 'default')}",
        )
        self.mj_model, self.control_dt = self.env.sys.mj_model, float(self.env.dt)

    @staticmethod
    def qpos(state: Any) -> jax.Array:
        return state.pipeline_state.q


# --------------------------------------------------------------------------------------------
# Wrappers of one environment


@struct.dataclass
class TimeLimitState:
    inner: Any
    elapsed: jax.Array  # [] steps taken in the current episode


class TimeLimit:
    """Truncates an episode after `spec.max_episode_steps` steps, unless that step terminated it."""

    def __init__(self, env: Env) -> None:
        self.env, self.spec = env, env.spec

    def reset(self, key: jax.Array) -> tuple[TimeLimitState, TimeStep]:
        state, ts = self.env.reset(key)
        return TimeLimitState(state, jnp.zeros((), jnp.int32)), ts

    def step(self, state: TimeLimitState, action: jax.Array) -> tuple[TimeLimitState, TimeStep]:
        inner, ts = self.env.step(state.inner, action)
        elapsed = state.elapsed + 1
        truncated = ts.truncated | ((elapsed >= self.spec.max_episode_steps) & ~ts.terminated)
        return TimeLimitState(inner, elapsed), ts.replace(truncated=truncated)


@struct.dataclass
class AutoResetState:
    inner: Any
    key: jax.Array


class AutoReset:
    """Starts a new episode inside `step` when one ends. `obs` becomes the new episode's first
    observation; `final_obs`, the flags and the reward stay those of the step that ended it."""

    def __init__(self, env: Env) -> None:
        self.env, self.spec = env, env.spec

    def reset(self, key: jax.Array) -> tuple[AutoResetState, TimeStep]:
        key, reset_key = jax.random.split(key)
        state, ts = self.env.reset(reset_key)
        return AutoResetState(state, key), ts

    def step(self, state: AutoResetState, action: jax.Array) -> tuple[AutoResetState, TimeStep]:
        inner, ts = self.env.step(state.inner, action)
        key, reset_key = jax.random.split(state.key)
        fresh, fresh_ts = self.env.reset(reset_key)
        done = ts.terminated | ts.truncated
        inner = jax.tree.map(lambda new, old: jnp.where(done, new, old), fresh, inner)
        ts = ts.replace(obs=jnp.where(done, fresh_ts.obs, ts.obs), final_obs=ts.obs)
        return AutoResetState(inner, key), ts


class VectorEnv:
    """`num_envs` copies of one JAX environment, auto-reset, stepped in one vmapped call."""

    def __init__(self, env: Env, num_envs: int) -> None:
        self.env = AutoReset(TimeLimit(env))
        self.spec, self.num_envs = env.spec, num_envs

    def reset(self, key: jax.Array) -> tuple[Any, TimeStep]:
        return jax.vmap(self.env.reset)(jax.random.split(key, self.num_envs))

    def step(self, state: Any, action: jax.Array) -> tuple[Any, TimeStep]:
        return jax.vmap(self.env.step)(state, action)


# --------------------------------------------------------------------------------------------
# Wrappers of a batched environment


@struct.dataclass
class EpisodeStatisticsState:
    inner: Any
    episode_return: jax.Array  # [N] undiscounted return of the running episode
    episode_length: jax.Array  # [N]


class EpisodeStatistics:
    """Adds `info["episode_return"]` and `info["episode_length"]`: for an environment whose
    episode ended at this step, the raw return and length of that episode; 0 elsewhere."""

    def __init__(self, env: Env) -> None:
        self.env, self.spec = env, env.spec

    def reset(self, key: jax.Array) -> tuple[EpisodeStatisticsState, TimeStep]:
        state, ts = self.env.reset(key)
        zeros = jnp.zeros(ts.reward.shape)
        return EpisodeStatisticsState(state, zeros, zeros.astype(jnp.int32)), ts

    def step(self, state: EpisodeStatisticsState, action: jax.Array):
        inner, ts = self.env.step(state.inner, action)
        episode_return = state.episode_return + ts.reward
        episode_length = state.episode_length + 1
        done = ts.terminated | ts.truncated
        info = dict(
            ts.info,
            episode_return=jnp.where(done, episode_return, 0.0),
            episode_length=jnp.where(done, episode_length, 0),
        )
        state = EpisodeStatisticsState(
            inner, jnp.where(done, 0.0, episode_return), jnp.where(done, 0, episode_length)
        )
        return state, ts.replace(info=info)


class ClipAction:
    """Clips actions to the spec's bounds before the simulator sees them; the trainer's buffer
    keeps the unclipped sample, so log-probabilities stay those of the sampled action."""

    def __init__(self, env: Env) -> None:
        self.env, self.spec = env, env.spec
        self.low = jnp.asarray(env.spec.action_low, jnp.float32)
        self.high = jnp.asarray(env.spec.action_high, jnp.float32)

    def reset(self, key: jax.Array) -> tuple[Any, TimeStep]:
        return self.env.reset(key)

    def step(self, state: Any, action: jax.Array) -> tuple[Any, TimeStep]:
        return self.env.step(state, jnp.clip(action, self.low, self.high))


@struct.dataclass
class RunningMeanStd:
    """Mean and variance of a stream of batches (Chan et al.'s parallel update)."""

    mean: jax.Array
    var: jax.Array
    count: jax.Array

    @classmethod
    def zeros(cls, shape: tuple[int, ...]) -> "RunningMeanStd":
        # A tiny prior count keeps the first update well defined, as in Gym's wrappers.
        return cls(jnp.zeros(shape), jnp.ones(shape), jnp.asarray(1e-4))

    def update(self, batch: jax.Array) -> "RunningMeanStd":
        """batch: [B, *shape]."""
        batch_mean, batch_var = batch.mean(0), batch.var(0)
        batch_count = batch.shape[0]
        delta = batch_mean - self.mean
        count = self.count + batch_count
        mean = self.mean + delta * batch_count / count
        m2 = self.var * self.count + batch_var * batch_count + delta**2 * self.count * batch_count / count
        return RunningMeanStd(mean, m2 / count, count)

    def standardize(self, x: jax.Array) -> jax.Array:
        return (x - self.mean) / jnp.sqrt(self.var + 1e-8)

    def unstandardize(self, x: jax.Array) -> jax.Array:
        return x * jnp.sqrt(self.var + 1e-8) + self.mean


def normalize_observation(obs: jax.Array, stats: RunningMeanStd, clip: float) -> jax.Array:
    """(obs - mean) / std, clipped to +-clip. obs: [..., obs_size]."""
    return jnp.clip(stats.standardize(obs), -clip, clip)


def restart(env: Env, state: Any, key: jax.Array) -> tuple[Any, TimeStep]:
    """Fresh episodes in every environment that keep the running statistics in `state`, for a
    resumed run whose simulators were not in its checkpoint: the normalisers' `restart`, a plain
    reset for environments that keep no statistics."""
    return env.restart(state, key) if hasattr(env, "restart") else env.reset(key)


@struct.dataclass
class NormalizeObservationState:
    inner: Any
    obs_stats: RunningMeanStd


class NormalizeObservation:
    """Normalises observations (and final observations) by running statistics of the
    observations seen so far, updated on every batch, then clips them.

    With `enabled=False` observations pass through unchanged and the statistics stay at their
    initial values, so the state keeps one layout either way."""

    def __init__(self, env: Env, clip: float, enabled: bool = True) -> None:
        self.env, self.spec, self.clip, self.enabled = env, env.spec, clip, enabled

    def reset(self, key: jax.Array) -> tuple[NormalizeObservationState, TimeStep]:
        state, ts = self.env.reset(key)
        stats = RunningMeanStd.zeros((self.spec.observation_size,))
        return self._output(state, stats, ts)

    def restart(self, state: NormalizeObservationState, key: jax.Array) -> tuple[NormalizeObservationState, TimeStep]:
        # The statistics are the checkpoint's, not updated, so that they go on as if never stopped.
        inner, ts = restart(self.env, state.inner, key)
        return self._output(inner, state.obs_stats, ts, update=False)

    def step(self, state: NormalizeObservationState, action: jax.Array):
        inner, ts = self.env.step(state.inner, action)
        return self._output(inner, state.obs_stats, ts)

    def _output(self, inner: Any, stats: RunningMeanStd, ts: TimeStep, update: bool = True):
        if not self.enabled:
            return NormalizeObservationState(inner, stats), ts
        if update:
            stats = stats.update(ts.obs)
        return NormalizeObservationState(inner, stats), ts.replace(
            obs=normalize_observation(ts.obs, stats, self.clip),
            final_obs=normalize_observation(ts.final_obs, stats, self.clip),
        )


@struct.dataclass
class NormalizeRewardState:
    inner: Any
    discounted_return: jax.Array  # [N]
    return_stats: RunningMeanStd


class NormalizeReward:
    """Scales rewards by `scale`, then (if `normalize`) divides them by the running standard
    deviation of the discounted return and clips them, as Gym's NormalizeReward did for the
    paper. The discounted return restarts when an episode ends."""

    def __init__(self, env: Env, gamma: float, clip: float, scale: float, normalize: bool) -> None:
        self.env, self.spec = env, env.spec
        self.gamma, self.clip, self.scale, self.normalize = gamma, clip, scale, normalize

    def reset(self, key: jax.Array) -> tuple[NormalizeRewardState, TimeStep]:
        state, ts = self.env.reset(key)
        return NormalizeRewardState(state, jnp.zeros(ts.reward.shape), RunningMeanStd.zeros(())), ts

    def restart(self, state: NormalizeRewardState, key: jax.Array) -> tuple[NormalizeRewardState, TimeStep]:
        inner, ts = restart(self.env, state.inner, key)
        return NormalizeRewardState(inner, jnp.zeros(ts.reward.shape), state.return_stats), ts

    def step(self, state: NormalizeRewardState, action: jax.Array):
        inner, ts = self.env.step(state.inner, action)
        reward = ts.reward * self.scale
        discounted = state.discounted_return * self.gamma + reward
        stats = state.return_stats.update(discounted)
        if self.normalize:
            reward = jnp.clip(reward / jnp.sqrt(stats.var + 1e-8), -self.clip, self.clip)
        discounted = jnp.where(ts.terminated | ts.truncated, 0.0, discounted)
        return NormalizeRewardState(inner, discounted, stats), ts.replace(reward=reward)


# --------------------------------------------------------------------------------------------
# Registry

# Brax's physics tasks; not its `fast`, a stand-in with no physics system for Brax's own tests.
BRAX_ENVS = (
    "ant", "halfcheetah", "hopper", "humanoid", "humanoidstandup",
    "inverted_double_pendulum", "inverted_pendulum", "pusher", "reacher", "swimmer", "walker2d",
)  # fmt: skip


class MissingExtraError(ValueError):
    """An environment needs an optional dependency that is not installed."""

    def __init__(self, name: str, module: str, extra: str) -> None:
        super().__init__(f"env {name!r} needs {module}, which is not installed: pip install -e '.[{extra}]'")


def _gym(name: str) -> Env:
    from rpo_jax import gym_suite

    return gym_suite.Pendulum() if name == "Pendulum-v1" else gym_suite.bipedal_walker()


def _dmc(task: str) -> Env:
    from rpo_jax import dmc_suite

    return dmc_suite.make(task)


def _pybullet(name: str) -> Env:
    from rpo_jax import pybullet_suite

    return pybullet_suite.make(name)


def _mjx_dmc(task: str) -> Env:
    from rpo_jax import playground_suite

    return playground_suite.PlaygroundEnv(task)


def _suite_specs() -> dict[str, EnvSpec]:
    # The suites' modules import their simulators only when an environment is built, so their
    # static specs are available without the optional dependencies. They import this module,
    # hence the import here rather than at the top.
    from rpo_jax import dmc_suite, gym_suite, playground_suite, pybullet_suite

    return gym_suite.SPECS | pybullet_suite.SPECS | dmc_suite.SPECS | playground_suite.SPECS


REGISTRY: dict[str, Callable[[], Env]] = (
    {"cartpole": Cartpole}
    | {f"brax/{name}": (lambda name=name: BraxEnv(name)) for name in BRAX_ENVS}
    | {f"gym/{name}": (lambda name=name: _gym(name)) for name in ("Pendulum-v1", "BipedalWalker-v3")}
    | {f"pybullet/{name}": (lambda name=name: _pybullet(name)) for name in ("Ant", "Minitaur")}
    | {f"dmc/{task}": (lambda task=task: _dmc(task)) for task in dmc_tasks.TASKS}
    | {f"mjx-dmc/{task}": (lambda task=task: _mjx_dmc(task)) for task in dmc_tasks.PLAYGROUND_NAMES}
)
REGISTRY["ballbalance"] = lambda: importlib.import_module("rpo_jax.ballbalance").BallBalance()  # imports envs


# Observation size, action size and backend of Brax's environments, so that listing them does
# not build their systems (minutes on a CPU); tests/test_registry.py checks them against the
# built environments.
BRAX_SPECS = {
    "ant": (27, 8, "generalized"), "fast": (2, 1, "default"), "halfcheetah": (17, 6, "generalized"),
    "hopper": (11, 3, "generalized"), "humanoid": (244, 17, "generalized"),
    "humanoidstandup": (244, 17, "generalized"), "inverted_double_pendulum": (8, 1, "generalized"),
    "inverted_pendulum": (4, 1, "generalized"), "pusher": (23, 7, "generalized"),
    "reacher": (11, 2, "generalized"), "swimmer": (8, 2, "generalized"), "walker2d": (17, 6, "generalized"),
}  # fmt: skip


def env_spec(name: str) -> EnvSpec:
    """The static facts of `name` without building it (or its optional dependencies)."""
    if name not in REGISTRY:
        raise ValueError(f"unknown env {name!r}; valid names: {', '.join(REGISTRY)}")
    if name.startswith("brax/"):
        obs_size, action_size, backend = BRAX_SPECS[name.removeprefix("brax/")]
        high = (1.0,) * action_size
        return EnvSpec(name, obs_size, action_size, tuple(-h for h in high), high, 1000, f"brax-{backend}")
    suite_specs = _suite_specs()
    if name in suite_specs:
        return suite_specs[name]
    spec = getattr(REGISTRY[name], "spec", None)
    return spec if isinstance(spec, EnvSpec) else REGISTRY[name]().spec


def make_env(name: str) -> Env:
    """The environment registered under `name`: a single (unbatched) JAX environment, or a
    host-side one (`host.HostEnv`) that only exists batched. `vectorize` batches either.
    A missing optional dependency raises `MissingExtraError` (a ValueError) naming the
    extra to install."""
    if name not in REGISTRY:
        raise ValueError(f"unknown env {name!r}; valid names: {', '.join(REGISTRY)}")
    return REGISTRY[name]()


def vectorize(env: Env, num_envs: int) -> Env:
    """`num_envs` auto-resetting copies of `env` behind the batched protocol: vmapped for a JAX
    environment, a pool of host simulators for a host-side one."""
    return env.vectorize(num_envs) if hasattr(env, "vectorize") else VectorEnv(env, num_envs)


def make_vector_env(name: str, num_envs: int) -> Env:
    """`num_envs` auto-resetting copies of `name` behind the batched protocol."""
    return vectorize(make_env(name), num_envs)


def main(argv: list[str] | None = None) -> int:
    """`python -m rpo_jax.envs`: one line per registered environment."""
    argv = sys.argv[1:] if argv is None else argv
    if argv:
        print(f"error: python -m rpo_jax.envs takes no arguments, got {' '.join(argv)}", file=sys.stderr)
        return 2
    rows = [("name", "backend", "obs", "act", "episode")]
    for name in REGISTRY:
        spec = env_spec(name)
        rows.append((name, spec.backend, str(spec.observation_size), str(spec.action_size), str(spec.max_episode_steps)))
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    for row in rows:
        print("  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
