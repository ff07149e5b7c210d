"""A policy acting in environments, shared by every consumer: the environment training steps
(`wrap_for_training`), the policy of a trained or training run (`Policy`) and what its first
episodes score (`first_episodes`: the returns and the task's own metrics).

`Policy` and `first_episodes` serve `rpo_jax.load_policy`, `rpo_jax.evaluate` and the
evaluation during training (`--eval-every`), so that all three act and count returns the same way.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from rpo_jax import envs
from rpo_jax.config import TANH_NORMAL, Config
from rpo_jax.errors import UsageError
from rpo_jax.networks import Actor, policy_distribution, to_action

# act(obs, key=None, deterministic=True) -> action: a `Policy`, or one jitted (`load_policy`, `make_policy`).
ActFn = Callable[..., jax.Array]


@struct.dataclass
class Policy:
    """The actor of a run with its parameters and observation statistics, acting within the
    environment's action bounds [low, high]. The config says how observations are normalised and
    which distribution the actor's outputs parameterise. `part`: the policy's part of the
    environment's observation (`EnvSpec.part`), None where it reads all `observation_size`."""

    config: Config = struct.field(pytree_node=False)
    actor: Actor = struct.field(pytree_node=False)
    params: Any
    obs_stats: envs.RunningMeanStd
    low: jax.Array
    high: jax.Array
    part: tuple[int, int] | None = struct.field(pytree_node=False, default=None)
    observation_size: int = struct.field(pytree_node=False, default=0)

    def __call__(self, obs: jax.Array, key: jax.Array | None = None, deterministic: bool = True) -> jax.Array:
        """The action for a raw observation [obs_size] or batch [B, obs_size]: normalised by the
        training statistics as in training, the policy's location (the Gaussian's mean, the
        Laplace's and Gumbel's location; the default, which every evaluation and export uses) or,
        with `deterministic=False`, a sample drawn with `key`, clipped to the environment's bounds
        as the environment would. With observations of named parts, `obs` is the policy's part
        (a robot's own sensors) or the whole observation, of which it reads that part."""
        if not deterministic and key is None:
            raise ValueError("a sampled action (deterministic=False) needs a key: policy(obs, key, deterministic=False)")
        obs, stats = self.policy_part(obs)
        if self.config.normalize_obs:
            obs = envs.normalize_observation(obs, stats, self.config.obs_clip)
        loc, log_scale = self.actor.apply(self.params, obs)
        sample = loc if deterministic else policy_distribution(loc, log_scale, self.config.dist).sample(seed=key)
        return jnp.clip(to_action(sample, self.config.dist, self.low, self.high), self.low, self.high)

    def policy_part(self, obs: jax.Array) -> tuple[jax.Array, envs.RunningMeanStd]:
        """The policy's part of `obs` (unchanged where it is that part already) and of the statistics."""
        if self.part is None:
            return obs, self.obs_stats
        start, stop = self.part
        stats = part_statistics(self.obs_stats, self.part)
        if obs.shape[-1] == self.observation_size:
            obs = obs[..., start:stop]
        elif obs.shape[-1] != stop - start:
            raise ValueError(f"the policy takes {stop - start} or {self.observation_size} observations, got {obs.shape[-1]}")
        return obs, stats


def part_statistics(stats: envs.RunningMeanStd, part: tuple[int, int] | None) -> envs.RunningMeanStd:
    """The observation statistics of the part [start, stop) of the observation (all: None)."""
    if part is None:
        return stats
    return stats.replace(mean=stats.mean[..., part[0] : part[1]], var=stats.var[..., part[0] : part[1]])


def make_actor(config: Config, spec: envs.EnvSpec) -> Actor:
    """The actor of `config` in the environment of `spec`, reading the policy's part of its observation."""
    state_dependent = config.dist == TANH_NORMAL
    if state_dependent and not np.isfinite([*spec.action_low, *spec.action_high]).all():
        raise UsageError(f"--dist tanh-normal squashes actions onto finite bounds; {spec.name}'s are unbounded")
    reads = spec.part(spec.policy_obs_key)
    return Actor(spec.action_size, tuple(config.hidden_sizes), config.activation, reads, config.init_log_scale, state_dependent)


def policy_of(config: Config, spec: envs.EnvSpec, params: Any, obs_stats: envs.RunningMeanStd) -> Policy:
    """A run's `Policy` in the environment of `spec`, reading the policy's part of its observation."""
    actor = dataclasses.replace(make_actor(config, spec), reads=None)  # `Policy` hands it the part
    low, high = jnp.asarray(spec.action_low), jnp.asarray(spec.action_high)
    return Policy(config, actor, params, obs_stats, low, high, spec.part(spec.policy_obs_key), spec.observation_size)


@struct.dataclass
class FirstEpisodes:
    """What `first_episodes` measures of each of its episodes, each [episodes]."""

    returns: jax.Array  # undiscounted, the environment's own rewards (no scaling or normalisation)
    finished: jax.Array  # whether it ended within max_episode_steps
    task_metrics: dict[str, jax.Array]  # each of the task's own metrics (`info["task/<name>"]`) summed over the episode


def first_episodes(env: envs.Env, policy: ActFn, episodes: int, key: jax.Array, deterministic: bool) -> FirstEpisodes:
    """Jittable: the first episode of each of `episodes` fresh copies of `env` under `policy`.
    `env` may be batched already, with `episodes` copies."""
    vec = envs.EpisodeStatistics(env if isinstance(env, envs.BatchedEnv) else envs.vectorize(env, episodes))
    reset_key, act_key = jax.random.split(key)
    state, ts = vec.reset(reset_key)
    zeros = jnp.zeros(episodes)
    # The task's metrics, by the names its steps give them (none for most tasks).
    action = jax.ShapeDtypeStruct((episodes, env.spec.action_size), jnp.float32)
    sums = {name[len("task/") :]: zeros for name in jax.eval_shape(vec.step, state, action)[1].info if name.startswith("task/")}

    def step(carry, key):
        state, obs, returns, finished, sums = carry
        state, ts = vec.step(state, policy(obs, key, deterministic))
        done = ts.terminated | ts.truncated
        returns = jnp.where(done & ~finished, ts.info["episode_return"], returns)
        sums = {name: total + jnp.where(finished, 0.0, ts.info["task/" + name]) for name, total in sums.items()}
        return (state, ts.obs, returns, finished | done, sums), None

    carry = (state, ts.obs, zeros, zeros.astype(bool), sums)
    (_, _, returns, finished, sums), _ = jax.lax.scan(step, carry, jax.random.split(act_key, env.spec.max_episode_steps))
    return FirstEpisodes(returns, finished, sums)


def first_episode_returns(
    env: envs.Env, policy: ActFn, episodes: int, key: jax.Array, deterministic: bool
) -> tuple[jax.Array, jax.Array]:
    """Jittable: `first_episodes`' returns and whether each episode ended, both [episodes]."""
    measured = first_episodes(env, policy, episodes, key, deterministic)
    return measured.returns, measured.finished


def wrap_for_training(
    env: envs.Env, config: Config, env_shards: int = 1, axis_name: str | None = None
) -> envs.NormalizeObservation:
    """The batched environment the trainer steps: `env` itself if it is already batched, else
    `config.num_envs / env_shards` auto-resetting copies (one device's share), under the episode
    statistics, action clipping and the reward and observation normalisers."""
    num_envs = config.num_envs // env_shards
    if not isinstance(env, envs.BatchedEnv):
        # The first rollout starts the environments, so the training program resets in one place.
        env = envs.vectorize(env, num_envs, defer_start=True)
    elif env.num_envs != num_envs:
        raise ValueError(f"num_envs must match the vector environment's {env.num_envs}, got {num_envs}")
    vec = envs.EpisodeStatistics(env)
    vec = envs.ClipAction(vec)
    vec = envs.NormalizeReward(vec, config.gamma, config.reward_clip, config.reward_scale, config.normalize_reward, axis_name)
    return envs.NormalizeObservation(vec, config.obs_clip, enabled=config.normalize_obs, axis_name=axis_name)
