"""The registry of environments by name: the built-in ones of every simulator family, and any
that a user adds with `register_env`.

Every built-in environment is registered with its static spec, so that listing them
(`python -m rpo_jax.envs`) or reading a spec builds nothing and imports no simulator: the
family modules import theirs only when an environment is built.
"""

from __future__ import annotations

import dataclasses
import difflib
from typing import Callable

from rpo_jax.envs import ballbalance, brax, cartpole, dmc, dmc_tasks, gym, playground, pybullet
from rpo_jax.envs.protocol import BatchedEnv, Env, EnvSpec
from rpo_jax.envs.wrappers import vectorize
from rpo_jax.errors import UsageError


@dataclasses.dataclass
class _Entry:
    factory: Callable[[], Env]
    spec: EnvSpec | None  # None until known: declared at registration, or read from a built env


_REGISTRY: dict[str, _Entry] = {}


def register_env(
    name: str, factory: Callable[[], Env], spec: EnvSpec | None = None, *, replace: bool = False
) -> None:
    """Registers `factory` (no arguments; returns a single JAX environment or a host-side one)
    under `name`. With `spec`, listing and `env_spec` use it without building the environment;
    without, `env_spec` builds it once to read its spec. A name already taken raises
    ValueError unless `replace`."""
    if name in _REGISTRY and not replace:
        raise ValueError(f"env {name!r} is already registered; pass replace=True to replace it")
    _REGISTRY[name] = _Entry(factory, spec)


def env_names() -> tuple[str, ...]:
    """Every registered name, in registration order."""
    return tuple(_REGISTRY)


def _entry(name: str) -> _Entry:
    if name not in _REGISTRY:
        close = difflib.get_close_matches(name, _REGISTRY, n=5)
        hint = f" (did you mean {', '.join(close)}?)" if close else ""
        raise UsageError(f"unknown env {name!r}{hint}; python -m rpo_jax.envs lists them")
    return _REGISTRY[name]


def env_spec(name: str) -> EnvSpec:
    """The static facts of `name`: the declared spec, without building the environment (or
    importing its optional dependencies); else that of the environment, built once."""
    entry = _entry(name)
    if entry.spec is None:
        entry.spec = entry.factory().spec
    return entry.spec


def make_env(name: str) -> Env:
    """The environment registered under `name`: a single (unbatched) JAX environment, or a
    host-side one (`host.HostEnv`) that only exists batched. `vectorize` batches either.
    A missing optional dependency raises `MissingExtraError` (a UsageError) naming the
    extra to install."""
    return _entry(name).factory()


def make_vector_env(name: str, num_envs: int) -> BatchedEnv:
    """`num_envs` auto-resetting copies of `name` behind the batched protocol."""
    return vectorize(make_env(name), num_envs)


# --------------------------------------------------------------------------------------------
# The built-in environments, in the order `python -m rpo_jax.envs` lists them

register_env("cartpole", cartpole.Cartpole, cartpole.SPEC)
for _name in brax.BRAX_ENVS:
    register_env(f"brax/{_name}", lambda name=_name: brax.BraxEnv(name), brax.SPECS[f"brax/{_name}"])
register_env("gym/Pendulum-v1", gym.Pendulum, gym.PENDULUM_SPEC)
register_env("gym/BipedalWalker-v3", gym.bipedal_walker, gym.BIPEDAL_WALKER_SPEC)
for _name in pybullet.GYM_IDS:
    register_env(f"pybullet/{_name}", lambda name=_name: pybullet.make(name), pybullet.SPECS[f"pybullet/{_name}"])
for _task in dmc_tasks.TASKS:
    register_env(f"dmc/{_task}", lambda task=_task: dmc.make(task), dmc.SPECS[f"dmc/{_task}"])
for _task in dmc_tasks.PLAYGROUND_NAMES:
    register_env(
        f"mjx-dmc/{_task}", lambda task=_task: playground.PlaygroundEnv(task), playground.SPECS[f"mjx-dmc/{_task}"]
    )
register_env("ballbalance", ballbalance.BallBalance, ballbalance.SPEC)
del _name, _task
