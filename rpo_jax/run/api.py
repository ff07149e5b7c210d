"""From Python to a run directory that every command reads (`load_policy`, `python -m
rpo_jax.evaluate`, `export`, `report`): `train_runs`, the command line's training loop with a
progress function, and `save_run`, a state trained in memory (`make_train`, `Trainer.train`).

    trainer = make_trainer(Config(total_timesteps=100_000), make_env("cartpole"))
    state, metrics = jax.jit(trainer.train)(jax.random.PRNGKey(0))
    save_run("runs/mine", trainer, state, metrics, env="cartpole")
"""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path
from typing import Any, Sequence

import jax
import numpy as np

from rpo_jax import envs, ppo
from rpo_jax.config import Config
from rpo_jax.errors import UsageError
from rpo_jax.run import chunks
from rpo_jax.run.directory import hold_lock, write_rows
from rpo_jax.run.options import Processes, RunSpec
from rpo_jax.run.plan import RunPlan, config_record, describe_runs, new_plan
from rpo_jax.run.records import logged_rows, record_returns, summarise
from rpo_jax.run.saved_policy import params_bytes


def train_runs(
    out: str | Path, env: str, config: Config, spec: RunSpec | None = None,
    progress_fn: chunks.ProgressFn | None = None, sinks: Sequence[chunks.Sink] = (),
) -> dict[str, Any]:  # fmt: skip
    """Trains the runs of `spec` (seeds, sweeps, logging, checkpoints, evaluation; its `out` is
    replaced by `out`, a new or empty directory) as `python -m rpo_jax.train` does, and returns
    summary.json's content. After each chunk of updates `progress_fn(env_steps, metrics)` gets the
    steps done per run and a dict of floats (`records.progress_metrics`: the trainer's metrics,
    `eval_return` after an evaluation, `sps`), as Brax's progress_fn; `sinks` get the logged rows."""
    plan = new_plan(env, config, dataclasses.replace(spec or RunSpec(), out=Path(out)))
    return chunks.run_plan(plan, sinks, progress_fn)


def save_run(
    out: str | Path, trainer: ppo.Trainer, state: ppo.TrainState, metrics: ppo.Metrics, *, env: str, seed: int = 0,
    train_seconds: float | None = None,
) -> Path:  # fmt: skip
    """Writes the run directory `out` (new or empty) of a state trained in memory: config.json,
    metrics.jsonl (the logged updates of `metrics`), params.msgpack and summary.json, as
    `python -m rpo_jax.train` writes them, so that `load_policy`, evaluate, export and report read
    it. `state` and `metrics` are `trainer.train(key)`'s (leaves [...] and [num_updates, ...]) or
    its vmap over keys' ([runs, ...]), all with the trainer's config's hyperparameters; `env` is
    the name `make_env` built the environment from (rebuilt by evaluate), `seed` the first run's
    recorded seed (run i: seed + i), and `train_seconds` the training time, for steps/s (else
    null). Returns `out`; ValueError for a state or metrics that do not fit the trainer."""
    if np.ndim(state.update) == 0:  # one run: the runs' axis that every file has
        state, metrics = jax.tree.map(lambda leaf: leaf[None], (state, metrics))
    state, metrics = jax.device_get((state, metrics))
    check_saved(trainer.config, state, metrics)
    check_env_name(env, trainer.env.spec)
    spec = RunSpec(out=Path(out), seed=seed, num_seeds=len(state.update))
    plan = new_plan(env, trainer.config, spec, Processes(devices=1))
    existed = plan.out.exists()
    with hold_lock(plan.out):
        try:
            write_saved(plan, trainer, state, metrics, train_seconds)
        except BaseException:
            shutil.rmtree(plan.out)  # nothing half-written: the same call can write it again
            if existed:  # the user's own empty directory stays
                plan.out.mkdir()
            raise
    return plan.out


def check_saved(config: Config, state: ppo.TrainState, metrics: ppo.Metrics) -> None:
    """Refuses, as ValueError, runs that config.json could not describe: hyperparameters other
    than the config's (a sweep: save each point's runs with a trainer of its config) or metrics
    of another number of updates or runs."""
    expected = ppo.Hyperparams.from_config(config)
    for name, values in state.hparams._asdict().items():
        wanted = np.float32(getattr(expected, name))
        if not np.all(np.asarray(values, np.float32) == wanted):
            raise ValueError(
                f"save_run: the state's {name} is {np.asarray(values).tolist()}, its trainer's config's {float(wanted):g}; "
                "save the runs of each hyperparameter setting with a trainer of that config"
            )
    shape = np.shape(metrics.episode_return)
    if shape != (len(state.update), config.num_updates):
        raise ValueError(
            f"save_run: metrics are of {shape[-1]} updates of {shape[0]} run(s), the state of {len(state.update)} run(s) "
            f"and the config has {config.num_updates} updates; give the metrics of the training that made the state"
        )


def check_env_name(env: str, spec: envs.EnvSpec) -> None:
    """Refuses an `env` name whose environment is not the trainer's (its spec differs): evaluate
    and export rebuild the environment from the name, and its policy would not fit it."""
    named = envs.env_spec(env)
    fields = ("name", "observation_size", "action_size", "action_low", "action_high")
    if any(tuple(np.ravel(getattr(named, f))) != tuple(np.ravel(getattr(spec, f))) for f in fields):
        raise UsageError(
            f"save_run: env={env!r} is {named.name} ({named.observation_size} observations, {named.action_size} actions), "
            f"but the trainer's environment is {spec.name} ({spec.observation_size}, {spec.action_size}); give the name "
            "make_env built the trainer's environment from"
        )


def write_saved(
    plan: RunPlan, trainer: ppo.Trainer, state: ppo.TrainState, metrics: ppo.Metrics, train_seconds: float | None
) -> None:  # fmt: skip
    """The files of `save_run`, summary.json last (it marks a finished run)."""
    runs, directory, updates = describe_runs(plan, [{}]), plan.run_dir, plan.config.num_updates
    directory.write_config({**config_record(plan, runs, [], trainer.env.spec), **plan.placement.describe()})
    sps = updates * plan.config.batch_size * len(runs) / train_seconds if train_seconds else None
    rows = logged_rows(plan, runs, metrics, 0, updates, sps)
    with directory.append_metrics() as metrics_file:
        write_rows(metrics_file, rows)
    logged_returns: dict[str, list[list[float]]] = {"episode_return": [[] for _ in runs]}
    record_returns(rows, logged_returns)
    directory.write_params(params_bytes(state.params, trainer.observation_statistics(state)))
    directory.write_summary(summarise(plan, [{}], runs, logged_returns, None, {"train_seconds": train_seconds}))
