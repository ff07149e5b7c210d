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
import importlib.machinery
import importlib.util
import inspect
import re
import sys
from pathlib import Path
from typing import Callable

from rpo_jax.envs import (
    ballbalance, brax, cartpole, dmc, dmc_tasks, gym, gymnasium, mjx_dmc, mjx_robots, perturbations, pybullet,
    robot_tasks, robots,
)  # fmt: skip
from rpo_jax.envs.check import missing_members
from rpo_jax.envs.protocol import BatchedEnv, Env, EnvSpec, MissingExtraError
from rpo_jax.envs.wrappers import vectorize
from rpo_jax.errors import UsageError


# The suites with names beyond those registered (`serves(name)`, `unlisted(name, import_factory)`):
# any Gymnasium task, the robots with options of their own on either path.
OPEN_SUITES = (gymnasium, robots, mjx_robots)


@dataclasses.dataclass
class _Entry:
    factory: Callable[[], Env]
    spec: EnvSpec | None  # None until known: declared at registration, or read from a built env


_REGISTRY: dict[str, _Entry] = {}


def register_env(name: str, factory: Callable[[], Env], spec: EnvSpec | None = None, *, replace: bool = False) -> None:
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
    base, separator, ranges = name.partition(perturbations.SEPARATOR)
    if separator:  # a task whose physics or sensing is drawn per episode: `cartpole+mass=0.8:1.2`
        inner, parsed = _entry(base), perturbations.parse_ranges(name, ranges)
        spec = dataclasses.replace(inner.spec, name=name) if inner.spec else None
        return _Entry(lambda: perturbations.perturbed(inner.factory(), parsed, name), spec)
    # Not kept in the registry, so that they are never listed and a changed module is read again.
    suite = next((suite for suite in OPEN_SUITES if suite.serves(name)), None)
    if suite is not None:
        entry = _Entry(*suite.unlisted(name, import_factory))  # its options checked first, by the suite
        imported_module(name)  # refuses a module name it would import that is not absolute
        return entry
    if ":" in name:
        return _Entry(lambda: import_factory(name)(), None)
    close = difflib.get_close_matches(name, _REGISTRY, n=5)
    if name.startswith("gym/"):
        close.append(gymnasium.PREFIX + name.removeprefix("gym/"))  # Gymnasium's tasks beyond the paper's
    hint = f" (did you mean {', '.join(close)}?)" if close else ""
    raise UsageError(
        f"unknown env {name!r}{hint}; python -m rpo_jax.envs lists them, or give an import path package.module:factory"
    )


# An absolute module name: dotted identifiers, never a relative import (.m) or a file path (a/../b).
MODULE_NAME = re.compile(r"[A-Za-z_]\w*(\.[A-Za-z_]\w*)*")


def imported_module(name: str) -> str | None:
    """The module that building `name` imports by name: an import path's, that of a Gymnasium id
    `module:Env-v0` (Gymnasium imports it), or an MJX robot's randomiser (`?randomize=module:fn`);
    None for a registered name. UsageError for a module name that is not absolute (relative, or a
    file path), which is never imported."""
    name = name.partition(perturbations.SEPARATOR)[0]  # the ranges of a perturbed name import nothing
    if name.startswith(robot_tasks.MJX_PREFIX):
        name = str(robot_tasks.parse_options(name, name.partition("?")[2]).get("randomize", ""))
    if name in _REGISTRY or ":" not in name:
        return None
    module_name = name.removeprefix(gymnasium.PREFIX).partition(":")[0]
    if not MODULE_NAME.fullmatch(module_name):
        raise UsageError(
            f"env {name!r}: {module_name!r} is not a module name; an import path is package.module:factory "
            "with an absolute, dotted module name (no relative import, no file path)"
        )
    return module_name


def check_import_outside(name: str, directory: Path) -> None:
    """Refuses, as UsageError, an environment `name` (read from a run directory's config.json)
    whose module would be imported from inside `directory`: code shipped with a run directory
    is never run, nor a module of Python's standard library, which holds no environment but
    functions that config.json could name to run (`os:abort`). Found without importing anything."""
    module_name = imported_module(name)
    if module_name is None:
        return
    top = module_name.partition(".")[0]
    if top in sys.stdlib_module_names or top in sys.builtin_module_names:
        raise UsageError(
            f"{directory}: its environment {name!r} names {module_name}, a module of Python's standard library, which "
            "holds no environment; its config.json was edited, so it is not run"
        )
    inside = Path(directory).resolve()
    for location in module_locations(module_name):
        if location.resolve().is_relative_to(inside):
            raise UsageError(
                f"{directory}: its environment {name!r} would import {module_name} from {location}, inside the run "
                "directory, whose code is never run; if you trust it, run from another directory with that module "
                "on PYTHONPATH outside the run directory"
            )


def module_locations(module_name: str) -> list[Path]:
    """The files and directories that importing `module_name` would load it and its packages
    from, found by the import system's finders without running any of them."""
    locations: list[Path] = []
    search: list[str] | None = None
    parts = module_name.split(".")
    for depth, part in enumerate(parts, 1):
        try:
            if depth == 1:
                spec = importlib.util.find_spec(part)
            else:
                spec = importlib.machinery.PathFinder.find_spec(".".join(parts[:depth]), search)
        except KeyError:  # a namespace package in one not imported: its portions, found as the finder would
            search = [str(Path(entry, part)) for entry in search or () if Path(entry, part).is_dir()]
            locations += map(Path, search)
            continue
        except (ImportError, ValueError):
            break
        if spec is None:  # not found: importing it fails, and says so
            break
        if spec.has_location and spec.origin:
            locations.append(Path(spec.origin))
        search = list(spec.submodule_search_locations or [])
        locations += map(Path, search)
        if not search:  # a module: the last part
            break
    return locations


def import_factory(path: str, arguments: int = 0) -> Callable[..., Env]:
    """The callable named by the import path `package.module:factory` (a dotted attribute after
    the colon is followed), checked to be callable with `arguments` positional arguments (an
    environment's factory takes none; a robot's randomiser, model and key)."""
    module_name, _, attribute = path.partition(":")
    if not module_name or not attribute:
        raise UsageError(f"env {path!r}: an import path is package.module:factory, e.g. my_package.envs:make_env")
    imported_module(path)  # refuses relative and file-system module names
    try:
        module = importlib.import_module(module_name)
    except ImportError as error:
        raise UsageError(
            f"env {path!r}: cannot import {module_name} ({type(error).__name__}: {error}); "
            "it must be installed or on PYTHONPATH (the current directory is, under python -m)"
        ) from None
    except (Exception, SystemExit) as error:  # the module's own code failed (or exited) as it ran
        raise UsageError(f"env {path!r}: importing {module_name} raised {_described(error)}") from None
    try:
        factory = functools.reduce(getattr, attribute.split("."), module)
    except AttributeError:
        raise UsageError(f"env {path!r}: module {module_name} has no attribute {attribute}") from None
    try:
        inspect.signature(factory).bind(*[None] * arguments)
    except TypeError:
        takes = f"{arguments} positional arguments" if arguments else "no arguments"
        raise UsageError(f"env {path!r}: {attribute} is not a callable that takes {takes}") from None
    except ValueError:  # a builtin without a signature: it is called as it is
        pass
    return factory


def _described(error: BaseException) -> str:
    """An exception as one line: its type and its message's first line."""
    if isinstance(error, SystemExit):
        return f"SystemExit (exit code {error.code!r}): it must return, not exit"
    first = (str(error).strip().splitlines() or [""])[0][:300]
    return f"{type(error).__name__}: {first}" if first else type(error).__name__


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
    extra to install; an environment that lacks what the protocol needs, or a factory that
    raises or exits, a UsageError naming what it lacks or what it raised."""
    factory = _entry(name).factory
    try:
        env = factory()
    except UsageError:  # a missing extra, an unknown Gymnasium id: said already
        raise
    except (Exception, SystemExit) as error:  # a user's factory failed (or exited): one line, not a traceback
        raise UsageError(f"env {name!r}: its factory raised {_described(error)}") from None
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
register_env("gym/BipedalWalker-v3", lambda: gymnasium.make("BipedalWalker-v3", "gym/BipedalWalker-v3"), gym.BIPEDAL_WALKER_SPEC)
for _name in pybullet.GYM_IDS:
    register_env(f"pybullet/{_name}", lambda name=_name: pybullet.make(name), pybullet.SPECS[f"pybullet/{_name}"])
for _task in dmc_tasks.TASKS:
    register_env(f"dmc/{_task}", lambda task=_task: dmc.make(task), dmc.SPECS[f"dmc/{_task}"])
for _task in dmc_tasks.PLAYGROUND_NAMES:
    register_env(f"mjx-dmc/{_task}", lambda task=_task: mjx_dmc.PlaygroundEnv(task), mjx_dmc.SPECS[f"mjx-dmc/{_task}"])
register_env("ballbalance", ballbalance.BallBalance, ballbalance.SPEC)
for _name in robots.SPECS:
    register_env(_name, lambda name=_name: robots.make(name), robots.SPECS[_name])
for _name in mjx_robots.SPECS:
    register_env(_name, lambda name=_name: mjx_robots.make(name, import_factory), mjx_robots.SPECS[_name])
del _name, _task


# The optional extras (pyproject.toml): the names they provide (by prefix) and the modules they install.
EXTRAS = {
    "gym": (("gym/BipedalWalker-v3", "gymnasium/"), ("gymnasium", "Box2D")),
    "dmc": (("dmc/", robots.PREFIX), ("envpool",)),
    "pybullet": (("pybullet/",), ("pybullet", "pybullet_envs")),
    "playground": (("mjx-dmc/", mjx_robots.PREFIX), ("mujoco_playground",)),
}


def missing_modules(extra: str) -> list[str]:
    """The modules of `extra` that are not installed, found without importing them (one that
    sys.modules holds as None cannot be imported either)."""
    return [module for module in EXTRAS[extra][1] if sys.modules.get(module, ...) is None or not importlib.util.find_spec(module)]


def check_installed(name: str) -> None:
    """Refuses (MissingExtraError, one line) an environment whose extra is not installed, before
    anything is built or printed."""
    for extra, (prefixes, _) in EXTRAS.items():
        if name.startswith(prefixes) and (missing := missing_modules(extra)):
            raise MissingExtraError(name, missing[0], extra)
