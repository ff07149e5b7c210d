"""Evaluation: the policy of every run on fresh copies of the environment, as one program
vmapped over the runs. Training calls it between chunks of updates (`rpo_jax.run.chunks`), with
random numbers of its own; `python -m rpo_jax.evaluate` calls the same program on a run
directory's saved runs (`saved_evaluation`), so that, given the same episodes and keys, it
reproduces an evaluation logged in training bit for bit: another XLA program (one run under a
plain `jax.jit`) may round differently, and a chaotic task (Cartpole) amplifies that."""

from __future__ import annotations

from typing import Any, Callable, Sequence

import jax
import numpy as np

from rpo_jax import envs, ppo
from rpo_jax.acting import Policy, first_episodes, policy_of
from rpo_jax.config import Config

# The streams folded into each run's key for evaluation and for videos, so that neither touches
# training's random numbers.
STREAMS = (0x5EED, 0x71DE0)

# (runs' evaluation_inputs, keys [runs, 2]) -> (returns [runs, episodes], their means [runs], the
# task's metrics {name: [runs, episodes]}, each summed over an episode)
EvaluationProgram = Callable[[dict[str, Any], jax.Array], tuple[jax.Array, jax.Array, dict[str, jax.Array]]]


def run_policy(config: Config, env: envs.Env) -> Callable[[dict[str, Any]], Policy]:
    """A run's deterministic-capable `Policy` from its `evaluation_inputs`."""
    return lambda inputs: policy_of(config, env.spec, inputs["actor"], inputs["obs_stats"])


def stream_keys(keys: jax.Array, stream: int) -> jax.Array:
    """The runs' keys [runs, 2] of one of `STREAMS`, from their seeds' keys [runs, 2]."""
    return jax.vmap(jax.random.fold_in, in_axes=(0, None))(keys, stream)


def compile_evaluation(config: Config, env: envs.Env, episodes: int, deterministic: bool = True) -> EvaluationProgram:
    """The evaluation of every run, jitted for one device: the policy (deterministic unless told;
    normalised as in training, with the statistics of the moment) on `episodes` fresh copies of
    the environment, scored by the environment's own rewards (no scaling or normalisation), each
    run's key folded with its update count. For a host-side environment the copies are a pool of
    their own simulators. It takes the real runs' `evaluation_inputs` on the host, wherever the
    runs train, and compiles at its first call."""
    copies, make_policy = envs.vectorize(env, episodes), run_policy(config, env)

    def evaluate(inputs: dict[str, Any], key: jax.Array) -> tuple[jax.Array, jax.Array, dict[str, jax.Array]]:
        policy = make_policy(inputs)
        key = jax.random.fold_in(key, inputs["update"])
        measured = first_episodes(copies, policy, episodes, key, deterministic=deterministic)
        return measured.returns, measured.returns.mean(), measured.task_metrics

    program = jax.jit(jax.vmap(evaluate))
    if not isinstance(copies, envs.BatchedHostEnv):
        return program

    def evaluate_and_close(inputs: dict[str, Any], keys: jax.Array) -> tuple[jax.Array, jax.Array, dict[str, jax.Array]]:
        # Every evaluation builds its own pools of simulators; nothing steps them afterwards.
        results = jax.block_until_ready(program(inputs, keys))
        copies.close()
        return results

    return evaluate_and_close


def evaluation_inputs(trainer: ppo.Trainer, state: ppo.TrainState) -> dict[str, Any]:
    """What an evaluation reads of a (placed) training state: the actor, the observation
    statistics and the update count."""
    return {"actor": state.params["actor"], "obs_stats": trainer.observation_statistics(state), "update": state.update}


def saved_evaluation(
    saved: tuple[Config, dict[str, Any], Any, envs.RunningMeanStd], env: envs.Env, episodes: int, seeds: Sequence[int],
    deterministic: bool,
) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray], Callable[[int], Policy]]:  # fmt: skip
    """Training's evaluation program on every run of a finished run directory (`saved_policy.load_runs`'s
    `saved`) after its last update, each run's episodes chosen by its seed in `seeds` (its own
    seed gives the episodes of its final evaluation in training). Returns the returns [runs,
    episodes], their means [runs] (as training logs them), the task's metrics {name: [runs,
    episodes]} summed over each episode, and each run's `Policy` by its index."""
    config, _, actor_params, stats = saved
    # The update count as the training state holds it: int32, after the last update.
    inputs = {"actor": actor_params, "obs_stats": stats, "update": np.full(len(seeds), config.num_updates, np.int32)}
    keys = stream_keys(jax.vmap(jax.random.PRNGKey)(np.asarray(seeds)), STREAMS[0])
    returns, means, task_metrics = compile_evaluation(config, env, episodes, deterministic)(inputs, keys)
    make_policy = run_policy(config, env)
    task_metrics = {name: np.asarray(value) for name, value in task_metrics.items()}
    return np.asarray(returns), np.asarray(means), task_metrics, lambda run: make_policy(jax.tree.map(lambda x: x[run], inputs))
