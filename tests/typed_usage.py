"""Code a user writes with the library, which a type checker must accept (tests/test_library.py
runs mypy on it): the lazy exports of `rpo_jax` are seen with their real types, not `Any`."""

import jax
import numpy as np

import rpo_jax
from rpo_jax import Config, RunSpec, load_policy, make_env, make_policy, make_trainer, save_run, train_runs


def train_and_act(out: str) -> np.ndarray:
    config: Config = rpo_jax.Config(total_timesteps=10_000)
    trainer = make_trainer(config, make_env("cartpole"))
    state, metrics = jax.jit(trainer.train)(jax.random.PRNGKey(0))
    policy = make_policy(trainer, state)
    action: jax.Array = policy(np.zeros(4, np.float32))
    saved = save_run(out, trainer, state, metrics, env="cartpole", seed=1)
    summary: dict = train_runs(saved.parent / "more", "cartpole", config, RunSpec(num_seeds=2), progress_fn=lambda steps, m: None)
    assert summary and load_policy(saved)(np.zeros(4, np.float32)) is not None
    return np.asarray(action)
