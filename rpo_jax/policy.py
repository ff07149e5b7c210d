"""A trained policy: loading it from a run directory written by `python -m rpo_jax.train`, the
action it takes, and its returns on fresh episodes.

`act` and `first_episode_returns` are jittable and shared by `load_policy`, by
`rpo_jax.evaluate` and by the evaluation during training (`--eval-every`), so that all three
act and count returns the same way.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
from flax import serialization

from rpo_jax import envs, ppo
from rpo_jax.config import Config
from rpo_jax.errors import UsageError
from rpo_jax.networks import Actor, policy_distribution
from rpo_jax.rundir import PARAMS_FILE, RunDir

# policy(obs, key, deterministic) -> action
Policy = Callable[..., jax.Array]


def act(
    config: Config, actor: Actor, actor_params: Any, obs_stats: envs.RunningMeanStd, low: jax.Array, high: jax.Array,
    obs: jax.Array, key: jax.Array, deterministic: bool,
) -> jax.Array:  # fmt: skip
    """The action for a raw observation [obs_size] or batch [B, obs_size]: normalised by the
    training statistics as in training, sampled from the policy (its location when
    `deterministic`: the Gaussian's mean, the Laplace's and Gumbel's location) and clipped to
    the environment's bounds, as the environment would."""
    if config.normalize_obs:
        obs = envs.normalize_observation(obs, obs_stats, config.obs_clip)
    loc, log_scale = actor.apply(actor_params, obs)
    action = loc if deterministic else policy_distribution(loc, log_scale, config.dist).sample(seed=key)
    return jnp.clip(action, low, high)


def first_episode_returns(
    env: envs.Env, policy: Policy, episodes: int, key: jax.Array, deterministic: bool
) -> tuple[jax.Array, jax.Array]:
    """Jittable: the undiscounted return of the first episode of each of `episodes` fresh
    copies of `env` (its own rewards, no scaling or normalisation), and whether it ended within
    max_episode_steps. Both [episodes]. `env` may be batched already, with `episodes` copies."""
    vec = envs.EpisodeStatistics(env if isinstance(env, envs.BatchedEnv) else envs.vectorize(env, episodes))
    reset_key, act_key = jax.random.split(key)
    state, ts = vec.reset(reset_key)

    def step(carry, key):
        state, obs, returns, finished = carry
        state, ts = vec.step(state, policy(obs, key, deterministic))
        done = ts.terminated | ts.truncated
        returns = jnp.where(done & ~finished, ts.info["episode_return"], returns)
        return (state, ts.obs, returns, finished | done), None

    zeros = jnp.zeros(episodes)
    carry = (state, ts.obs, zeros, zeros.astype(bool))
    (_, _, returns, finished), _ = jax.lax.scan(step, carry, jax.random.split(act_key, env.spec.max_episode_steps))
    return returns, finished


def load_policy(run_dir: str | Path, run: int = 0) -> Policy:
    """Returns a jitted `policy(obs, key, deterministic=False) -> action` (see `act`). `run`
    indexes the runs (seeds x sweep points) trained together, as listed in config.json."""
    config, spec, actor_params, stats = load_run(run_dir, run)
    actor, _ = ppo.make_networks(config, spec["action_size"])
    low, high = jnp.asarray(spec["action_low"]), jnp.asarray(spec["action_high"])

    def policy(obs: jax.Array, key: jax.Array, deterministic: bool = False) -> jax.Array:
        return act(config, actor, actor_params, stats, low, high, obs, key, deterministic)

    return jax.jit(policy, static_argnames="deterministic")


def load_run(run_dir: str | Path, run: int = 0) -> tuple[Config, dict[str, Any], Any, envs.RunningMeanStd]:
    """One run's config, environment spec (as config.json records it), actor parameters and
    observation statistics."""
    directory = RunDir(Path(run_dir))
    saved_run = directory.read_config()
    if not 0 <= run < len(saved_run["runs"]):
        raise ValueError(f"run must be in [0, {len(saved_run['runs'])}), got {run}")
    try:
        saved = serialization.msgpack_restore(directory.read_params())
        actor_params = jax.tree.map(lambda x: jnp.asarray(x[run]), saved["params"]["actor"])
        stats = envs.RunningMeanStd(**{k: jnp.asarray(v[run]) for k, v in saved["obs_stats"].items()})
    except (ValueError, KeyError, TypeError, IndexError) as error:  # msgpack's errors are ValueErrors
        raise UsageError(f"{directory.path / PARAMS_FILE} is damaged ({error}); rpo_jax.train did not write it whole") from None
    if not all(bool(jnp.isfinite(leaf).all()) for leaf in jax.tree.leaves((actor_params, stats))):
        raise UsageError(f"{directory.path / PARAMS_FILE}: run {run}'s parameters are not finite (NaN or inf)")
    return Config.from_dict(saved_run["config"]), saved_run["env_spec"], actor_params, stats
