"""rpo_jax: PPO and Robust Policy Optimization on JAX, with thousands of environments in one XLA program."""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.3.0"  # the one declaration: pyproject.toml reads it

# Imported on first use, so that `import rpo_jax` (and every command's --help) loads no JAX.
_EXPORTS = {
    "Config": "rpo_jax.config", "PRESETS": "rpo_jax.envs.recipes", "ALGORITHMS": "rpo_jax.config",
    "make_train": "rpo_jax.ppo", "make_trainer": "rpo_jax.ppo", "load_policy": "rpo_jax.run.saved_policy",
    "make_policy": "rpo_jax.run.saved_policy", "save_run": "rpo_jax.run.api", "train_runs": "rpo_jax.run.api",
    "RunSpec": "rpo_jax.run.options", "register_env": "rpo_jax.envs", "make_env": "rpo_jax.envs", "check_env": "rpo_jax.envs",
}  # fmt: skip

# What type checkers and IDEs read instead of `__getattr__`: the same names, from the same modules
# (tests/test_library.py checks that the two lists agree).
if TYPE_CHECKING:  # `X as X`: re-exported, for type checkers
    from rpo_jax.config import ALGORITHMS as ALGORITHMS
    from rpo_jax.envs.recipes import PRESETS as PRESETS
    from rpo_jax.config import Config as Config
    from rpo_jax.envs import check_env as check_env
    from rpo_jax.envs import make_env as make_env
    from rpo_jax.envs import register_env as register_env
    from rpo_jax.ppo import make_train as make_train
    from rpo_jax.ppo import make_trainer as make_trainer
    from rpo_jax.run.api import save_run as save_run
    from rpo_jax.run.api import train_runs as train_runs
    from rpo_jax.run.options import RunSpec as RunSpec
    from rpo_jax.run.saved_policy import load_policy as load_policy
    from rpo_jax.run.saved_policy import make_policy as make_policy

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'rpo_jax' has no attribute {name!r}")
    return getattr(importlib.import_module(_EXPORTS[name]), name)


def __dir__() -> list[str]:
    """The public names and the module's dunders, without importing anything: what `dir(rpo_jax)` and completion show."""
    return sorted({*_EXPORTS, *(name for name in globals() if name.startswith("__"))})
