"""rpo_jax: PPO and Robust Policy Optimization on JAX, with thousands of environments in one XLA program."""

from rpo_jax.policy import load_policy
from rpo_jax.ppo import PRESETS, Config, make_train, make_trainer

__all__ = ["Config", "PRESETS", "load_policy", "make_train", "make_trainer"]
