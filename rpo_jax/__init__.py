"""rpo_jax: PPO and Robust Policy Optimization on JAX, with thousands of environments in one XLA program."""

import importlib
from typing import Any

# Imported on first use, so that `python -m rpo_jax.envs` runs its module once (the package
# would otherwise import rpo_jax.envs first, through rpo_jax.ppo).
_EXPORTS = {"load_policy": "rpo_jax.policy", **dict.fromkeys(["PRESETS", "Config", "make_train", "make_trainer"], "rpo_jax.ppo")}

__all__ = ["Config", "PRESETS", "load_policy", "make_train", "make_trainer"]


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'rpo_jax' has no attribute {name!r}")
    return getattr(importlib.import_module(_EXPORTS[name]), name)
