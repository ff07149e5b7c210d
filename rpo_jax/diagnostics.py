"""Counts of non-finite numbers in an update, for the runner's guard against training on them,
and the running statistics that training reads. Apart from `rpo_jax.ppo`, which returns them
beside each update's metrics (`Trainer.update(state, diagnose=True)`, `ppo.diagnosed_learn`),
since the update may run as two programs (`rpo_jax.parallel.devices`' epochs placement), each
counting its own half."""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from rpo_jax import envs
from rpo_jax.config import Config


@struct.dataclass
class Diagnostics:
    """Per-update counts of non-finite numbers, for the runner's guard; not logged, so that
    metrics.jsonl keeps its rows. Observations and rewards are the rollout's, as the trainer
    saw them (`count_rollout`); parameters and statistics are those after the update. A huge but
    finite observation overflows its normaliser's variance to inf while the normalised
    observations stay finite (zeros), so the statistics are counted apart: {"obs_stats.var": n}."""

    nonfinite_observations: jax.Array
    nonfinite_rewards: jax.Array
    nonfinite_parameters: jax.Array
    nonfinite_statistics: dict[str, jax.Array]

    @classmethod
    def of(cls, rollout_counts: tuple[jax.Array, jax.Array], state: Any, config: Config) -> "Diagnostics":
        """From the rollout's counts (`count_rollout`) and the state after the update."""
        statistics = {
            f"{name}.{field}": count_nonfinite(getattr(stats, field))
            for name, stats in running_statistics(state, config).items()
            for field in ("mean", "var", "count")
        }
        return cls(*rollout_counts, count_nonfinite(*jax.tree.leaves(state.params)), statistics)


# The magnitude past which an observation's square overflows float32, as the observation
# normaliser's variance does. Observations read raw (--no-normalize-obs) are counted past it, so
# that such a run stops as a normalised one does rather than train on them.
OVERFLOWING_OBSERVATION = math.sqrt(float(np.finfo(np.float32).max))  # numpy: no JAX computation at import


def count_nonfinite(*arrays: jax.Array) -> jax.Array:
    return sum((~jnp.isfinite(x)).sum() for x in arrays)


def count_rollout(traj: Any, config: Config) -> tuple[jax.Array, jax.Array]:
    """The rollout's non-finite observations (read raw: also those past `OVERFLOWING_OBSERVATION`)
    and rewards, for `Diagnostics.of`."""
    observations = (traj.obs, traj.final_obs)
    if config.normalize_obs:  # normalised observations are clipped: only NaN or inf can reach them
        observation_count = count_nonfinite(*observations)
    else:
        observation_count = sum((~(jnp.abs(x) <= OVERFLOWING_OBSERVATION)).sum() for x in observations)
    return observation_count, count_nonfinite(traj.reward, traj.episode_return)


def running_statistics(state: Any, config: Config) -> dict[str, envs.RunningMeanStd]:
    """The running statistics that training reads, by their field's name: the observation
    normaliser's (obs_stats), the reward normaliser's (return_stats) and the critic's targets'
    (value_stats), each where its option is on (an unused one is never read)."""
    found = jax.tree_util.tree_flatten_with_path(state.env_state, is_leaf=lambda x: isinstance(x, envs.RunningMeanStd))[0]
    named = {path[-1].name: stats for path, stats in found if isinstance(stats, envs.RunningMeanStd)}
    named["value_stats"] = state.value_stats
    used = {"obs_stats": config.normalize_obs, "return_stats": config.normalize_reward, "value_stats": config.normalize_value}
    return {name: stats for name, stats in named.items() if used.get(name, True)}
