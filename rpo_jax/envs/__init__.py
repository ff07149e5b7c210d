"""Environments behind one protocol, the wrappers that training puts around them, and a
registry of them by name.

- `protocol`: `Env` (`reset(key)`, `step(state, action)` and a static `EnvSpec`), its
  `TimeStep`, and the batched, host-side and renderable kinds.
- `wrappers`: the time limit, `VectorEnv` (vmapped, auto-resetting copies of one JAX environment),
  the batch wrappers (episode statistics, action clipping, reward and observation
  normalisation), and `vectorize`.
- `registry`: `make_env`, `env_spec`, `env_names`, `make_vector_env` and `register_env` for
  environments of one's own; `python -m rpo_jax.envs` lists the registered names. `make_env`
  also takes `gymnasium/<id>` and an import path `package.module:factory`.
- `check`: `check_env`, the protocol checked by running an environment
  (`python -m rpo_jax.envs --check NAME`).
- one module per simulator family: `cartpole` and `ballbalance` (MJX), `brax`, `mjx_dmc`
  (MuJoCo Playground's DeepMind Control on MJX), `robots` and `mjx_robots` (its robots on either
  path), and the host-side suites `gym`, `pybullet` and
  `dmc` (envpool's DeepMind Control) and `gymnasium` (any Gymnasium task with Box spaces),
  which `host` puts behind the batched protocol.

Importing this package imports no simulator; each family imports its own when one of its
environments is built.
"""

import os

# MuJoCo fixes its OpenGL backend at import. Without a display only an offscreen one can work,
# so pick EGL there unless the user chose (rendering is only used by `rpo_jax.evaluate --video`).
if not os.environ.get("DISPLAY"):
    os.environ.setdefault("MUJOCO_GL", "egl")

import importlib  # noqa: E402
from typing import Any  # noqa: E402

# Imported on first use, so that `python -m rpo_jax.envs --help` and the command lines that
# import this package for a submodule (`dmc_tasks`) load no JAX.
_EXPORTS = {
    "check_env": "check", "first_step_problems": "check",
    "BatchedHostEnv": "host", "HostEnv": "host", "SequentialSimulators": "host",
    "BatchedEnv": "protocol", "DrawsStarts": "protocol", "Env": "protocol", "EnvSpec": "protocol",
    "MissingExtraError": "protocol", "Renderable": "protocol", "Start": "protocol", "TimeStep": "protocol",
    "Vectorizable": "protocol", "first_step": "protocol",
    "env_names": "registry", "env_spec": "registry", "make_env": "registry", "make_vector_env": "registry",
    "register_env": "registry",
    "ClipAction": "wrappers", "DoneIsTermination": "wrappers", "EpisodeStatistics": "wrappers",
    "NormalizeObservation": "wrappers", "NormalizeReward": "wrappers", "RunningMeanStd": "wrappers",
    "TimeLimit": "wrappers", "VectorEnv": "wrappers", "normalize_observation": "wrappers", "vectorize": "wrappers",
}  # fmt: skip


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'rpo_jax.envs' has no attribute {name!r}")
    return getattr(importlib.import_module(f"rpo_jax.envs.{_EXPORTS[name]}"), name)


__all__ = [
    "BatchedEnv",
    "BatchedHostEnv",
    "ClipAction",
    "DoneIsTermination",
    "DrawsStarts",
    "Env",
    "EnvSpec",
    "EpisodeStatistics",
    "HostEnv",
    "MissingExtraError",
    "NormalizeObservation",
    "NormalizeReward",
    "Renderable",
    "RunningMeanStd",
    "SequentialSimulators",
    "Start",
    "TimeLimit",
    "TimeStep",
    "VectorEnv",
    "Vectorizable",
    "check_env",
    "env_names",
    "env_spec",
    "first_step",
    "first_step_problems",
    "make_env",
    "make_vector_env",
    "normalize_observation",
    "register_env",
    "vectorize",
]
