"""A trained policy: from a run directory written by `python -m rpo_jax.train` or
`rpo_jax.save_run` (`load_policy`, and the run's parts: `load_run`), or from a training state in
memory (`make_policy`). How it acts is `rpo_jax.acting`'s; params.msgpack's format is this
module's (`params_bytes` writes what `load_run` reads).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
from flax import serialization

from rpo_jax import envs, ppo
from rpo_jax.acting import ActFn, Policy, policy_of
from rpo_jax.config import ACTING_FIELDS, Config
from rpo_jax.errors import UsageError
from rpo_jax.run.directory import CONFIG_FILE, PARAMS_FILE, RunDir


def load_policy(run_dir: str | Path, run: int | None = None) -> ActFn:
    """Returns a jitted `policy(obs, key=None, deterministic=True) -> action` (see `acting.Policy`):
    the policy's location by default, a sample with a key and `deterministic=False`. `run`
    indexes the runs (seeds x sweep points) trained together, as listed in config.json; None: the
    first, or a population's best member (`RunDir.default_run`)."""
    config, spec, actor_params, stats = load_run(run_dir, run)
    return jitted_policy(policy_of(config, envs.EnvSpec.from_record(spec), actor_params, stats))


def make_policy(trainer: ppo.Trainer, state: ppo.TrainState, run: int | None = None) -> ActFn:
    """The policy `load_policy` would give of `state` saved, without files: a jitted
    `policy(obs, key=None, deterministic=True) -> action`. `state` is one run's (`make_train`'s
    `train(key)`, `trainer.init`) or, with `run` its index, one of several trained together
    (`jax.vmap(train)`)."""
    actor_params, stats = state.params["actor"], trainer.observation_statistics(state)
    batched = jnp.ndim(state.update) > 0
    if batched != (run is not None):
        raise ValueError(
            f"make_policy: give run (the index) with a state of several runs, and only then; got run={run} with "
            f"{'a state of ' + str(state.update.shape[0]) + ' runs' if batched else 'the state of one run'}"
        )
    if batched:
        if not 0 <= run < state.update.shape[0]:  # numpy's indexing would wrap a negative one, JAX's clamp any
            raise UsageError(f"make_policy: run must be in [0, {state.update.shape[0]}), got {run}")
        actor_params, stats = jax.tree.map(lambda leaf: leaf[run], (actor_params, stats))
    return jitted_policy(policy_of(trainer.config, trainer.env.spec, actor_params, stats))


def jitted_policy(policy: Policy) -> ActFn:
    """One run's `acting.Policy`, jitted (`deterministic` static)."""
    return jax.jit(policy.__call__, static_argnames="deterministic")


def params_bytes(params: Any, obs_stats: envs.RunningMeanStd) -> bytes:
    """params.msgpack's content: the parameters of every run (actor and critic) and their
    observation statistics, each leaf [runs, ...]."""
    return serialization.msgpack_serialize(serialization.to_state_dict({"params": params, "obs_stats": obs_stats}))


def load_run(run_dir: str | Path, run: int | None = None) -> tuple[Config, dict[str, Any], Any, envs.RunningMeanStd]:
    """One run's config, environment spec (as config.json records it), actor parameters and
    observation statistics; `run` as `load_policy`'s."""
    directory = RunDir(Path(run_dir))
    saved_run = directory.read_config()
    run, runs = directory.default_run() if run is None else run, len(saved_run["runs"])
    if not 0 <= run < runs:
        raise ValueError(f"run must be in [0, {runs}), got {run}")
    config, spec, actor_params, stats = _saved_runs(directory, saved_run)
    actor_params, stats = jax.tree.map(lambda x: jnp.asarray(x[run]), (actor_params, stats))
    if not all(bool(jnp.isfinite(leaf).all()) for leaf in jax.tree.leaves((actor_params, stats))):
        raise UsageError(f"{directory.path / PARAMS_FILE}: run {run}'s parameters are not finite (NaN or inf)")
    return config, spec, actor_params, stats


def load_runs(run_dir: str | Path) -> tuple[Config, dict[str, Any], Any, envs.RunningMeanStd]:
    """`load_run`'s parts of every run of the directory: the actor parameters and observation
    statistics with leaves [runs, ...] (numpy, as saved)."""
    directory = RunDir(Path(run_dir))
    return _saved_runs(directory, directory.read_config())


def _saved_runs(directory: RunDir, saved_run: dict[str, Any]) -> tuple[Config, dict[str, Any], Any, envs.RunningMeanStd]:
    """`load_runs` of `directory`, whose config.json record `saved_run` is."""
    check_acts_as_trained(directory, saved_run)
    runs = len(saved_run["runs"])
    try:
        saved = serialization.msgpack_restore(directory.read_params())
        actor_params, stats = saved["params"]["actor"], envs.RunningMeanStd(**saved["obs_stats"])
        if {len(leaf) for leaf in jax.tree.leaves((actor_params, stats))} != {runs}:
            raise ValueError(f"it does not hold the {runs} run(s) of config.json")
    except (ValueError, KeyError, TypeError, IndexError) as error:  # msgpack's errors are ValueErrors
        raise UsageError(f"{directory.path / PARAMS_FILE} is damaged ({error}); rpo_jax.train did not write it whole") from None
    return trained_config(saved_run), saved_run["env_spec"], actor_params, stats


def trained_config(saved_run: dict[str, Any]) -> Config:
    """The run's Config as it was trained (config.json's trained_with record, where it has one):
    a field edited afterwards that acting does not read (`check_acts_as_trained`) must not change
    what an evaluation computes from it, such as the update count its keys fold in."""
    config, trained = saved_run["config"], saved_run.get("trained_with")
    if isinstance(trained, dict):
        config = {**config, **{name: value for name, value in trained.items() if name in config}}
    return Config.from_dict(config)


def check_acts_as_trained(directory: RunDir, saved_run: dict[str, Any]) -> None:
    """Refuses a config.json edited after training in what the policy acts by, its environment
    or a config field of `ACTING_FIELDS`, where that differs from config.json's record of what
    the run was trained with (its trained_with). Other fields may differ: acting does not read them."""
    trained = saved_run.get("trained_with")
    if not isinstance(trained, dict):  # runs written before config.json recorded it
        return
    acting = {"env": saved_run["env"], **{name: saved_run["config"].get(name) for name in ACTING_FIELDS}}
    for name, value in acting.items():
        if name in trained and trained[name] != value:
            raise UsageError(
                f"{directory.path / CONFIG_FILE}: its {name} is {value!r}, but the run was trained with {trained[name]!r} "
                f"(its trained_with); the policy acts only as trained: put {name} back"
            )
