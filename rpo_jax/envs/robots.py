"""MuJoCo Playground's robots on envpool's C++ ports (`robot/<Task>`), stepped on the host: the
CPU path to the tasks that `rpo_jax.envs.mjx_robots` runs on MJX (`mjx-robot/<Task>`), the GPU
path.

envpool 1.2.5 (the `dmc` extra) ports Playground's locomotion and manipulation tasks with their
rewards, observation noise and pushes, and bundles the MuJoCo Menagerie models they need. A
locomotion task observes a dict: `state`, what the robot itself measures (joint angles and
velocities, gyro, gravity, the command; noisy), read by the policy, and `privileged_state`,
which adds what only a simulator knows (true velocities, contact forces, ...), read by the
critic: an asymmetric actor-critic. Their concatenation is the observation (`EnvSpec`'s
`observation_keys`), so an exported policy takes the `state` alone. Manipulation tasks with one
observation are flat.

A task's own settings (envpool's config fields: `noise_level`, `push_enable`, ...) are options
of its name: `robot/BerkeleyHumanoidJoystickFlatTerrain?push_enable=false,noise_level=0`
(`parse_name`). The name is what a run directory records, so evaluation and resumption build the
same environment. Episodes end by termination (a fall) or, at the task's limit, truncation.
"""

from __future__ import annotations

from typing import Any, Callable

from rpo_jax.envs import perturbations
from rpo_jax.envs.host import HostEnv
from rpo_jax.envs.protocol import EnvSpec, MissingExtraError
from rpo_jax.envs import robot_tasks
from rpo_jax.envs.robot_tasks import PREFIX, TASKS
from rpo_jax.errors import UsageError


def spec(task: str, name: str | None = None) -> EnvSpec:
    """The spec of `task` under `name` (its registered name `robot/<task>` by default)."""
    return robot_tasks.spec(task, name or PREFIX + task, "host")


SPECS = {PREFIX + task: spec(task) for task in TASKS}


def parse_name(name: str) -> tuple[str, dict[str, Any]]:
    """'robot/Go1JoystickFlatTerrain?noise_level=0,push_enable=false' -> the task and its options
    (numbers, true/false, or text), each checked against the task's settings; UsageError where a
    task or setting is unknown."""
    task, _, query = name.removeprefix(PREFIX).partition("?")
    if task not in TASKS:
        raise UsageError(f"env {name!r}: unknown robot task {task!r}; python -m rpo_jax.envs lists them")
    options = robot_tasks.parse_options(name, query)
    if options:
        settings = _settings(task)
        unknown = sorted(set(options) - set(settings))
        if unknown:
            raise UsageError(f"env {name!r}: {task} has no setting {', '.join(unknown)}; its settings: {', '.join(settings)}")
        for key, value in options.items():
            robot_tasks.check_option(name, key, value, settings[key])
    return task, options


# envpool's config fields that are not a task's own settings.
POOL_FIELDS = {
    "num_envs", "batch_size", "num_threads", "max_num_players", "thread_affinity_offset", "base_path", "seed",
    "env_seed", "gym_reset_return_info", "max_episode_steps", "frame_stack", "task_name",
}  # fmt: skip


def _settings(task: str) -> dict[str, Any]:
    """The task's own settings (envpool's config fields for it, less the pool's) and their values."""
    envpool = _import_envpool(PREFIX + task)
    config = envpool.make_spec(f"{task}-v1").config
    return {field: getattr(config, field) for field in config._fields if field not in POOL_FIELDS}


def _import_envpool(name: str) -> Any:
    try:
        import envpool
    except ImportError:
        raise MissingExtraError(name, "envpool", "dmc") from None
    return envpool


# The physics axes (`perturbations.MODEL_AXES`) that envpool's ports expose as settings: the
# position servos' stiffness and damping (kp, kd) are their actuators' strength.
SETTING_AXES = {"gain": ("kp", "kd")}


def serves(name: str) -> bool:
    """Whether `name` is one of this suite's unlisted names: a robot with options of its own
    (`robot/<Task>?KEY=VALUE,...`; the plain names are registered)."""
    return name.startswith(PREFIX) and "?" in name


def unlisted(name: str, import_function: Any) -> tuple[Callable[[], HostEnv], EnvSpec]:
    """The factory and the spec of `name`, one that `serves`, its options checked now."""
    task, _ = parse_name(name)
    return (lambda: make(name)), spec(task, name)


def make(name: str) -> HostEnv:
    """The host-side environment `name` (`robot/<Task>`, with options or not)."""
    _import_envpool(name)
    task, options = parse_name(name)
    return _host_env(task, options, name)


def _host_env(task: str, options: dict[str, Any], name: str) -> HostEnv:
    from rpo_jax.envs.envpool_pools import DrawnEnvpoolTask, EnvpoolSimulators

    facts = TASKS[task]
    keys = ["state", "privileged_state"] if facts.privileged_size else ["state"]
    metrics = metric_keys(task)

    def with_physics(factors: dict[str, float]) -> HostEnv:
        settings, changed = _settings(task), dict(options)
        for axis, factor in factors.items():
            fields = SETTING_AXES.get(axis, ())
            if not fields or not all(field in settings for field in fields):
                raise UsageError(
                    f"{name}: envpool's port has no setting that changes {axis} (it scales kp and kd for gain, where "
                    f"a task has them); its axes are {', '.join(perturbations.SIGNAL_AXES)}"
                )
            changed.update({field: options.get(field, settings[field]) * factor for field in fields})
        return _host_env(task, changed, name)

    return HostEnv(
        spec(task, name),
        lambda num_envs, seed: EnvpoolSimulators(
            f"{task}-v1", facts.action_size, keys, num_envs, seed, options, facts.megabytes, metrics
        ),
        # Drawn from envpool's default view of the task (camera -1), with the run's settings.
        lambda seed, width, height: DrawnEnvpoolTask(
            f"{task}-v1", keys, seed, width, height, 1.0 / options.get("ctrl_dt", facts.control_dt), options, -1
        ),
        with_physics=with_physics,
        task_metrics=metrics,
    )


def metric_keys(task: str) -> tuple[str, ...]:
    """What envpool's port reports beside each step: the scalar float fields of its result (each
    reward term as `reward_<term>`, a manipulator's `out_of_bounds`), Playground's `metrics`."""
    import numpy as np

    result = _import_envpool(PREFIX + task).make_spec(f"{task}-v1").observation_spec()
    return tuple(
        name for name in result._fields
        if getattr(getattr(result, name), "shape", None) == () and np.issubdtype(getattr(result, name).dtype, np.floating)
    )  # fmt: skip
