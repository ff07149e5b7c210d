"""A trained policy: loading it from a run directory written by `python -m rpo_jax.train`
(`load_policy`, and the run's parts: `load_run`). How it acts is `rpo_jax.acting`'s.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
from flax import serialization

from rpo_jax import envs, ppo
from rpo_jax.acting import ActFn, Policy
from rpo_jax.config import Config
from rpo_jax.errors import UsageError
from rpo_jax.rundir import PARAMS_FILE, RunDir


def load_policy(run_dir: str | Path, run: int | None = None) -> ActFn:
    """Returns a jitted `policy(obs, key, deterministic=False) -> action` (see `acting.Policy`). `run`
    indexes the runs (seeds x sweep points) trained together, as listed in config.json; None: the
    first, or a population's best member (`RunDir.default_run`)."""
    config, spec, actor_params, stats = load_run(run_dir, run)
    actor, _ = ppo.make_networks(config, spec["action_size"])
    policy = Policy(config, actor, actor_params, stats, jnp.asarray(spec["action_low"]), jnp.asarray(spec["action_high"]))
    return jax.jit(policy.__call__, static_argnames="deterministic")


def load_run(run_dir: str | Path, run: int | None = None) -> tuple[Config, dict[str, Any], Any, envs.RunningMeanStd]:
    """One run's config, environment spec (as config.json records it), actor parameters and
    observation statistics; `run` as `load_policy`'s."""
    directory = RunDir(Path(run_dir))
    run = directory.default_run() if run is None else run
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
