"""Wrappers around the protocol's environments: the per-environment ones that `VectorEnv` puts
around a single JAX environment (time limit, auto-reset), and the batch wrappers that training
puts around any batched environment (episode statistics, action clipping, reward and
observation normalisation). `vectorize` batches a single JAX environment or a host-side one.

Every batch wrapper defines `restart(state, key)` besides `reset`: fresh episodes in every
environment that keep the running statistics in `state`, for a resumed run whose simulators
were not in its checkpoint; and `draw_starts(state, key)`, which passes the trainer's call
before each rollout down to a `VectorEnv`'s pool of initial states (`DrawsStarts`), and
`defers_start`, whether that `VectorEnv` starts its environments at the first draw.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from rpo_jax.envs.protocol import BatchedEnv, DrawsStarts, Env, Start, TimeStep, Vectorizable, first_step

# --------------------------------------------------------------------------------------------
# Adapter of environments that report `done`


class DoneIsTermination:
    """Adapts `self.env`, whose `reset(key)` and `step(state, action)` return a state with `obs`,
    `reward` and `done` (Brax's and MuJoCo Playground's environments), to the protocol: `done`
    is a termination, and the time limit is left to `TimeLimit`."""

    env: Any

    def reset(self, key: jax.Array) -> tuple[Any, TimeStep]:
        state = self.env.reset(key)
        return state, first_step(state.obs)

    def step(self, state: Any, action: jax.Array) -> tuple[Any, TimeStep]:
        state = self.env.step(state, action)
        terminated = state.done.astype(bool)
        return state, TimeStep(state.obs, state.reward, terminated, jnp.zeros((), bool), state.obs)


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
class VectorEnvState:
    envs: Any  # [N] the environments' states, under their time limits
    starts: Any  # [N] fresh initial states, which the episodes that end take in turn
    start_obs: jax.Array  # [N, obs_size] their first observations
    next_start: jax.Array  # [] how many of `starts` have been taken
    started: jax.Array  # [] whether `envs` holds started episodes (not after a deferred reset)


def select(done: jax.Array, new: Any, old: Any) -> Any:
    """`new` where `done`, else `old`, leaf by leaf: `done` is [N] for pytrees with a leading
    [N] axis, or [] for any pytrees."""
    return jax.tree.map(lambda a, b: jnp.where(done.reshape(done.shape + (1,) * (a.ndim - 1)), a, b), new, old)


class VectorEnv:
    """`num_envs` copies of one JAX environment under `TimeLimit`, stepped in one vmapped call,
    and auto-reset: when an episode ends, `obs` becomes the new episode's first observation
    while `final_obs`, the flags and the reward stay those of the step that ended it.

    A new episode starts from the next unused state of a pool of `num_envs` fresh initial
    states (`starts`), drawn with the environment's own `reset` by `draw_starts`, which the
    trainer calls once before each rollout. So the reset is paid once per environment and
    rollout, not at every step inside the vmap as a select of a reset computed for every
    environment, and every episode still starts from its own draw of the reset distribution.
    Only when more episodes end between two draws than there are environments do later ones
    take the pool's states a second time, in turn.

    With `defer_start` (the trainer's), `reset` computes no reset: the environments start at
    the first `draw_starts`, from its pool, so that the program holds the reset once (XLA
    compiles each copy on its own, and for MJX models a reset is a large part of the program).
    The episodes that end in that first rollout then take the pool's states a second time."""

    def __init__(self, env: Env, num_envs: int, defer_start: bool = False) -> None:
        self.env = TimeLimit(env)
        self.spec, self.num_envs, self.defers_start = env.spec, num_envs, defer_start
        # Jitted, so that a program which resets in two places (the first state and the pools
        # of starts) traces the environment's reset once.
        self._reset = jax.jit(self.env.reset)

    def reset(self, key: jax.Array) -> tuple[VectorEnvState, TimeStep]:
        n = self.num_envs
        if self.defers_start:
            # Zeros laid out as the reset's states: the first draw replaces them all.
            shapes = jax.eval_shape(jax.vmap(self._reset), jax.random.split(key, n))
            states, ts = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), shapes)
            return VectorEnvState(states, states, ts.obs, jnp.zeros((), jnp.int32), jnp.zeros((), bool)), ts
        # The environments and the first pool in one vmapped reset: one copy of it to compile.
        states, ts = jax.vmap(self._reset)(jax.random.split(key, 2 * n))
        first, rest = (lambda x: x[:n]), (lambda x: x[n:])
        state = VectorEnvState(
            jax.tree.map(first, states), jax.tree.map(rest, states), ts.obs[n:], jnp.zeros((), jnp.int32),
            jnp.ones((), bool),
        )  # fmt: skip
        return state, jax.tree.map(first, ts)

    def draw_starts(self, state: VectorEnvState, key: jax.Array) -> tuple[VectorEnvState, Start]:
        """`state` with a new pool of initial states; after a deferred reset, with its
        environments started from that pool."""
        starts, ts = jax.vmap(self._reset)(jax.random.split(key, self.num_envs))
        envs = select(state.started, state.envs, starts)
        taken = jnp.where(state.started, 0, self.num_envs).astype(jnp.int32)
        return VectorEnvState(envs, starts, ts.obs, taken, jnp.ones((), bool)), Start(~state.started, ts.obs)

    def step(self, state: VectorEnvState, action: jax.Array) -> tuple[VectorEnvState, TimeStep]:
        envs, ts = jax.vmap(self.env.step)(state.envs, action)
        done = ts.terminated | ts.truncated
        # The k-th episode to end since the draw takes start k (mod N): a cumulative count, so
        # each ending episode gets a different start whichever environments they are.
        taken = (state.next_start + jnp.cumsum(done) - 1) % self.num_envs
        envs = select(done, jax.tree.map(lambda pool: pool[taken], state.starts), envs)
        obs = jnp.where(done[:, None], state.start_obs[taken], ts.obs)
        next_start = state.next_start + done.sum(dtype=jnp.int32)
        return state.replace(envs=envs, next_start=next_start), ts.replace(obs=obs, final_obs=ts.obs)


# --------------------------------------------------------------------------------------------
# Wrappers of a batched environment


@struct.dataclass
class EpisodeStatisticsState:
    inner: Any
    episode_return: jax.Array  # [N] undiscounted return of the running episode
    episode_length: jax.Array  # [N]


class EpisodeStatistics:
    """Adds `info["episode_return"]` and `info["episode_length"]`: for an environment whose
    episode ended at this step, the raw return and length of that episode; 0 elsewhere.

    The innermost batch wrapper: the others' `restart` ends in this one's, a plain reset."""

    def __init__(self, env: Env) -> None:
        self.env, self.spec = env, env.spec

    def reset(self, key: jax.Array) -> tuple[EpisodeStatisticsState, TimeStep]:
        state, ts = self.env.reset(key)
        zeros = jnp.zeros(ts.reward.shape)
        return EpisodeStatisticsState(state, zeros, zeros.astype(jnp.int32)), ts

    def restart(self, state: EpisodeStatisticsState, key: jax.Array) -> tuple[EpisodeStatisticsState, TimeStep]:
        # Nothing outlives an episode here: the running returns and lengths start again.
        return self.reset(key)

    @property
    def defers_start(self) -> bool:
        return isinstance(self.env, DrawsStarts) and self.env.defers_start

    def draw_starts(self, state: EpisodeStatisticsState, key: jax.Array) -> tuple[EpisodeStatisticsState, Start]:
        if not isinstance(self.env, DrawsStarts):
            # Host pools and other batched environments reset their episodes themselves.
            return state, Start(jnp.zeros((), bool), jnp.zeros((self.env.num_envs, self.spec.observation_size)))
        inner, start = self.env.draw_starts(state.inner, key)
        return state.replace(inner=inner), start

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
        state = EpisodeStatisticsState(inner, jnp.where(done, 0.0, episode_return), jnp.where(done, 0, episode_length))
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

    def restart(self, state: Any, key: jax.Array) -> tuple[Any, TimeStep]:
        return self.env.restart(state, key)

    @property
    def defers_start(self) -> bool:
        return self.env.defers_start

    def draw_starts(self, state: Any, key: jax.Array) -> tuple[Any, Start]:
        return self.env.draw_starts(state, key)

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

    def update(self, batch: jax.Array, axis_name: str | None = None) -> "RunningMeanStd":
        """batch: [B, *shape]. With `axis_name`, `batch` is this device's share of a batch split
        in equal shares over that device axis, and every device gets the statistics of the
        whole batch."""
        batch_mean, batch_var = batch.mean(0), batch.var(0)
        batch_count = batch.shape[0]
        if axis_name is not None:
            # Chan's merge of equal-sized shares: the mean of the means, and the mean of the
            # variances plus the spread of the means around the merged mean.
            merged_mean = jax.lax.pmean(batch_mean, axis_name)
            batch_var = jax.lax.pmean(batch_var + (batch_mean - merged_mean) ** 2, axis_name)
            batch_mean, batch_count = merged_mean, batch_count * jax.lax.psum(1, axis_name)
        delta = batch_mean - self.mean
        count = self.count + batch_count
        mean = self.mean + delta * batch_count / count
        m2 = self.var * self.count + batch_var * batch_count + delta**2 * self.count * batch_count / count
        return RunningMeanStd(mean, m2 / count, count)

    @property
    def std(self) -> jax.Array:
        """The standard deviation that standardises: never zero, where a feature is constant."""
        return jnp.sqrt(self.var + 1e-8)

    def standardize(self, x: jax.Array) -> jax.Array:
        return (x - self.mean) / self.std

    def unstandardize(self, x: jax.Array) -> jax.Array:
        return x * self.std + self.mean


def normalize_observation(obs: jax.Array, stats: RunningMeanStd, clip: float) -> jax.Array:
    """(obs - mean) / std, clipped to +-clip. obs: [..., obs_size]."""
    return jnp.clip(stats.standardize(obs), -clip, clip)


@struct.dataclass
class NormalizeObservationState:
    inner: Any
    obs_stats: RunningMeanStd


class NormalizeObservation:
    """Normalises observations (and final observations) by running statistics of the
    observations seen so far, updated on every batch, then clips them.

    With `enabled=False` observations pass through unchanged and the statistics stay at their
    initial values, so the state keeps one layout either way. With `axis_name`, the batch is
    split over that device axis and the statistics are merged over it (`RunningMeanStd.update`)."""

    def __init__(self, env: Env, clip: float, enabled: bool = True, axis_name: str | None = None) -> None:
        self.env, self.spec, self.clip, self.enabled, self.axis_name = env, env.spec, clip, enabled, axis_name

    def reset(self, key: jax.Array) -> tuple[NormalizeObservationState, TimeStep]:
        state, ts = self.env.reset(key)
        stats = RunningMeanStd.zeros((self.spec.observation_size,))
        # A deferred reset's observations are placeholders: the statistics take the first
        # observations at the first draw instead.
        return self._output(state, stats, ts, update=not self.env.defers_start)

    def restart(self, state: NormalizeObservationState, key: jax.Array) -> tuple[NormalizeObservationState, TimeStep]:
        # The statistics are the checkpoint's, not updated, so that they go on as if never stopped.
        inner, ts = self.env.restart(state.inner, key)
        return self._output(inner, state.obs_stats, ts, update=False)

    @property
    def defers_start(self) -> bool:
        return self.env.defers_start

    def draw_starts(self, state: NormalizeObservationState, key: jax.Array) -> tuple[NormalizeObservationState, Start]:
        inner, start = self.env.draw_starts(state.inner, key)
        if not self.enabled:
            return state.replace(inner=inner), start
        # Where the environments started here, their first observations count as a reset's do.
        stats = select(start.started, state.obs_stats.update(start.obs, self.axis_name), state.obs_stats)
        return NormalizeObservationState(inner, stats), start.replace(obs=normalize_observation(start.obs, stats, self.clip))

    @staticmethod
    def statistics(state: NormalizeObservationState) -> RunningMeanStd:
        """The running statistics of the observations in `state` (what a saved policy keeps)."""
        return state.obs_stats

    def step(self, state: NormalizeObservationState, action: jax.Array):
        inner, ts = self.env.step(state.inner, action)
        return self._output(inner, state.obs_stats, ts)

    def _output(self, inner: Any, stats: RunningMeanStd, ts: TimeStep, update: bool = True):
        if not self.enabled:
            return NormalizeObservationState(inner, stats), ts
        if update:
            stats = stats.update(ts.obs, self.axis_name)
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
    paper. The discounted return restarts when an episode ends. With `axis_name`, as in
    `NormalizeObservation`."""

    def __init__(self, env: Env, gamma: float, clip: float, scale: float, normalize: bool, axis_name: str | None = None) -> None:
        self.env, self.spec = env, env.spec
        self.gamma, self.clip, self.scale, self.normalize, self.axis_name = gamma, clip, scale, normalize, axis_name

    def reset(self, key: jax.Array) -> tuple[NormalizeRewardState, TimeStep]:
        state, ts = self.env.reset(key)
        return NormalizeRewardState(state, jnp.zeros(ts.reward.shape), RunningMeanStd.zeros(())), ts

    def restart(self, state: NormalizeRewardState, key: jax.Array) -> tuple[NormalizeRewardState, TimeStep]:
        inner, ts = self.env.restart(state.inner, key)
        return NormalizeRewardState(inner, jnp.zeros(ts.reward.shape), state.return_stats), ts

    @property
    def defers_start(self) -> bool:
        return self.env.defers_start

    def draw_starts(self, state: NormalizeRewardState, key: jax.Array) -> tuple[NormalizeRewardState, Start]:
        inner, start = self.env.draw_starts(state.inner, key)
        return state.replace(inner=inner), start

    def step(self, state: NormalizeRewardState, action: jax.Array):
        inner, ts = self.env.step(state.inner, action)
        reward = ts.reward * self.scale
        discounted = state.discounted_return * self.gamma + reward
        stats = state.return_stats.update(discounted, self.axis_name)
        if self.normalize:
            reward = jnp.clip(reward / stats.std, -self.clip, self.clip)
        discounted = jnp.where(ts.terminated | ts.truncated, 0.0, discounted)
        return NormalizeRewardState(inner, discounted, stats), ts.replace(reward=reward)


def vectorize(env: Env, num_envs: int, defer_start: bool = False) -> BatchedEnv:
    """`num_envs` auto-resetting copies of `env` behind the batched protocol: vmapped for a JAX
    environment (`defer_start` as in `VectorEnv`), a pool of host simulators for a host-side one."""
    return env.vectorize(num_envs) if isinstance(env, Vectorizable) else VectorEnv(env, num_envs, defer_start)
