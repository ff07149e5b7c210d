"""The registry of environments by name: the built-in ones of every simulator family, and any
that a user adds with `register_env`. `make_env` and `env_spec` also take two kinds of names
that are not listed: `gymnasium/<id>`, any Gymnasium task with Box spaces (`envs.gymnasium`),
and an import path `package.module:factory`, a callable (a function or a class) that takes no
arguments and returns an environment; run directories record either string as their `env`.

Every built-in environment is registered with its static spec, so that listing them
(`python -m rpo_jax.envs`) or reading a spec builds nothing and imports no simulator: the
family modules import theirs only when an environment is built.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import importlib
import inspect
from typing import Callable

from rpo_jax.envs import ballbalance, brax, cartpole, dmc, dmc_tasks, gym, gymnasium, playground, pybullet
from rpo_jax.envs.check import missing_members
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
    if name in _REGISTRY:
        return _REGISTRY[name]
    # Not kept in the registry, so that they are never listed and a changed module is read again.
    if name.startswith(gymnasium.PREFIX):
        return _Entry(lambda: gymnasium.make(name.removeprefix(gymnasium.PREFIX)), None)
    if ":" in name:
        return _Entry(lambda: import_factory(name)(), None)
    close = difflib.get_close_matches(name, _REGISTRY, n=5)
    if name.startswith("gym/"):
        close.append(gymnasium.PREFIX + name.removeprefix("gym/"))  # Gymnasium's tasks beyond the paper's
    hint = f" (did you mean {', '.join(close)}?)" if close else ""
    raise UsageError(
        f"unknown env {name!r}{hint}; python -m rpo_jax.envs lists them, "
        "or give an import path package.module:factory"
    )


def import_factory(path: str) -> Callable[[], Env]:
    """The callable named by the import path `package.module:factory` (a dotted attribute after
    the colon is followed), checked to be callable without arguments."""
    module_name, _, attribute = path.partition(":")
    if not module_name or not attribute:
        raise UsageError(f"env {path!r}: an import path is package.module:factory, e.g. my_package.envs:make_env")
    try:
        module = importlib.import_module(module_name)
    except ImportError as error:
        raise UsageError(
            f"env {path!r}: cannot import {module_name} ({type(error).__name__}: {error}); "
            "it must be installed or on PYTHONPATH (the current directory is, under python -m)"
        ) from None
    try:
        factory = functools.reduce(getattr, attribute.split("."), module)
    except AttributeError:
        raise UsageError(f"env {path!r}: module {module_name} has no attribute {attribute}") from None
    try:
        inspect.signature(factory).bind()
    except TypeError:
        raise UsageError(f"env {path!r}: {attribute} is not a callable that takes no arguments") from None
    except ValueError:  # a builtin without a signature: it is called as it is
        pass
    return factory


def env_spec(name: str) -> EnvSpec:
    """The static facts of `name`: the declared spec, without building the environment (or
    importing its optional dependencies); else that of the environment, built once."""
    entry = _entry(name)
    if entry.spec is None:
        entry.spec = make_env(name).spec
    return entry.spec


def make_env(name: str) -> Env:
    """The environment registered under `name`: a single (unbatched) JAX environment, or a
    host-side one (`host.HostEnv`) that only exists batched. `vectorize` batches either.
    A missing optional dependency raises `MissingExtraError` (a UsageError) naming the
    extra to install; an environment that lacks what the protocol needs, a UsageError naming
    what it lacks."""
    env = _entry(name).factory()
    missing = missing_members(env)
    if missing:
        raise UsageError(
            f"env {name!r}: its factory returned a {type(env).__name__}, which lacks {', '.join(missing)}; "
            "an environment has spec (an EnvSpec), reset(key) and step(state, action) (rpo_jax.envs.protocol.Env)"
        )
    return env


def make_vector_env(name: str, num_envs: int) -> BatchedEnv:
    """`num_envs` auto-resetting copies of `name` behind the batched protocol."""
    return vectorize(make_env(name), num_envs)


# --------------------------------------------------------------------------------------------
# The built-in environments, in the order `python -m rpo_jax.envs` lists them

register_env("cartpole", cartpole.Cartpole, cartpole.SPEC)
for _name in brax.BRAX_ENVS:
    register_env(f"brax/{_name}", lambda name=_name: brax.BraxEnv(name), brax.SPECS[f"brax/{_name}"])
register_env("gym/Pendulum-v1", gym.Pendulum, gym.PENDULUM_SPEC)
register_env(
    "gym/BipedalWalker-v3", lambda: gymnasium.make("BipedalWalker-v3", "gym/BipedalWalker-v3"), gym.BIPEDAL_WALKER_SPEC
)
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
