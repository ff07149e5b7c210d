"""Evaluation during training: the deterministic policy of every run on fresh copies of the
environment, compiled once and called between chunks of updates (`rpo_jax.runner`), with random
numbers of its own."""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp

from rpo_jax import envs, ppo
from rpo_jax.acting import Policy, first_episode_returns
from rpo_jax.plan import RunPlan

# The streams folded into each run's key for evaluation and for videos, so that neither touches
# training's random numbers.
STREAMS = (0x5EED, 0x71DE0)


def run_policy(trainer: ppo.Trainer, env: envs.Env) -> Callable[[dict[str, Any]], Policy]:
    """A run's deterministic-capable `Policy` from its `evaluation_inputs`."""
    low, high = jnp.asarray(env.spec.action_low), jnp.asarray(env.spec.action_high)
    return lambda inputs: Policy(trainer.config, trainer.actor, inputs["actor"], inputs["obs_stats"], low, high)


def compile_evaluation(plan: RunPlan, env: envs.Env, trainer: ppo.Trainer) -> Callable:
    """The evaluation of every run, jitted for one device: the deterministic policy (normalised as
    in training, with the statistics of the moment) on `eval_episodes` fresh copies of the
    environment, scored by the environment's own rewards (no scaling or normalisation). For a
    host-side environment the copies are a pool of their own simulators. It takes the real runs'
    `evaluation_inputs` on the host, wherever the runs train, and compiles at its first call."""
    copies, make_policy = envs.vectorize(env, plan.eval_episodes), run_policy(trainer, env)

    def evaluate(inputs: dict[str, Any], key: jax.Array) -> jax.Array:
        policy = make_policy(inputs)
        key = jax.random.fold_in(key, inputs["update"])
        returns, _ = first_episode_returns(copies, policy, plan.eval_episodes, key, deterministic=True)
        return returns.mean()

    program = jax.jit(jax.vmap(evaluate))
    if not isinstance(copies, envs.BatchedHostEnv):
        return program

    def evaluate_and_close(inputs: dict[str, Any], keys: jax.Array) -> jax.Array:
        # Every evaluation builds its own pools of simulators; nothing steps them afterwards.
        returns = jax.block_until_ready(program(inputs, keys))
        copies.close()
        return returns

    return evaluate_and_close


def evaluation_inputs(trainer: ppo.Trainer, state: ppo.TrainState) -> dict[str, Any]:
    """What an evaluation reads of a (placed) training state: the actor, the observation
    statistics and the update count."""
    return {"actor": state.params["actor"], "obs_stats": trainer.observation_statistics(state), "update": state.update}
