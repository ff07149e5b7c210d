"""Loading a trained policy from a run directory written by `python -m rpo_jax.train`."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
from flax import serialization

from rpo_jax import envs, ppo
from rpo_jax.config import Config
from rpo_jax.errors import UsageError
from rpo_jax.networks import policy_distribution
from rpo_jax.rundir import PARAMS_FILE, RunDir


def load_policy(run_dir: str | Path, run: int = 0) -> Callable[..., jax.Array]:
    """Returns a jitted `policy(obs, key, deterministic=False) -> action`.

    `obs` is a raw observation [obs_size] or a batch [B, obs_size]; the saved normaliser
    statistics are applied as in training. The action is sampled from the policy (its mean
    when `deterministic`; for Gumbel and Laplace policies, the location) and clipped to the
    environment's bounds, as the environment would. `run` indexes the runs (seeds x sweep
    points) trained together, as listed in config.json."""
    directory = RunDir(Path(run_dir))
    saved_run = directory.read_config()
    config = Config.from_dict(saved_run["config"])
    spec = saved_run["env_spec"]
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
    actor, _ = ppo.make_networks(config, spec["action_size"])
    low, high = jnp.asarray(spec["action_low"]), jnp.asarray(spec["action_high"])

    def policy(obs: jax.Array, key: jax.Array, deterministic: bool = False) -> jax.Array:
        if config.normalize_obs:
            obs = envs.normalize_observation(obs, stats, config.obs_clip)
        loc, log_scale = actor.apply(actor_params, obs)
        action = loc if deterministic else policy_distribution(loc, log_scale, config.dist).sample(seed=key)
        return jnp.clip(action, low, high)

    return jax.jit(policy, static_argnames="deterministic")
