"""rpo_jax: PPO and Robust Policy Optimization on JAX, with thousands of environments in one XLA program."""

import importlib
from typing import Any

__version__ = "0.2.0"  # the one declaration: pyproject.toml reads it

# Imported on first use, so that `import rpo_jax` (and every command's --help) loads no JAX.
_EXPORTS = {
    "Config": "rpo_jax.config", "PRESETS": "rpo_jax.config", "ALGORITHMS": "rpo_jax.config",
    "make_train": "rpo_jax.ppo", "make_trainer": "rpo_jax.ppo", "load_policy": "rpo_jax.policy",
    "register_env": "rpo_jax.envs", "make_env": "rpo_jax.envs", "check_env": "rpo_jax.envs",
}  # fmt: skip

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'rpo_jax' has no attribute {name!r}")
    return getattr(importlib.import_module(_EXPORTS[name]), name)
