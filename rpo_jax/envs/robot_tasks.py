"""MuJoCo Playground's robots that rpo_jax registers, as static data, so that the registry and
the experiments name them without importing a simulator or JAX (`spec` imports it when called),
and the options of their names, which both paths read (`robots`: envpool's ports on the host;
`mjx_robots`: MJX). Read from envpool 1.2.5's ports; tests/test_robots.py checks them against it."""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING, Any

from rpo_jax.errors import UsageError

if TYPE_CHECKING:
    from rpo_jax.envs.protocol import EnvSpec

PREFIX = "robot/"
MJX_PREFIX = "mjx-robot/"  # the same tasks on MJX (`mjx_robots`)
# The settings the command line gives any robot (`--obs-noise`, `--push`), by envpool's names; the
# MJX path reads them into Playground's config (`mjx_robots.CONFIG_PATHS`).
NOISE_LEVEL, PUSH_ENABLE = "noise_level", "push_enable"


@dataclasses.dataclass(frozen=True)
class RobotTask:
    """Static facts of one of Playground's tasks as envpool ports it."""

    action_size: int
    state_size: int
    privileged_size: int  # 0: one flat observation, read by both networks
    episode_steps: int
    control_dt: float  # seconds a step
    preset: str  # rpo_jax's preset of Playground's PPO config for it (`rpo_jax.config.PRESETS`)
    megabytes: float  # one envpool simulator's resident memory (benchmarks/lab/robot_memory.py)


TASKS = {
    # Locomotion: quadrupeds and humanoids following a velocity command, getting up, standing.
    "Go1JoystickFlatTerrain": RobotTask(12, 48, 123, 1000, 0.02, "go1-joystick", 58.1),
    "Go1JoystickRoughTerrain": RobotTask(12, 48, 123, 1000, 0.02, "go1-joystick", 46.6),
    "Go1Getup": RobotTask(12, 42, 91, 300, 0.02, "go1-getup", 55.9),
    "Go1Handstand": RobotTask(12, 45, 94, 500, 0.02, "go1-handstand", 52.8),
    "Go1Footstand": RobotTask(12, 45, 94, 500, 0.02, "go1-handstand", 54.8),
    "BerkeleyHumanoidJoystickFlatTerrain": RobotTask(12, 52, 114, 1000, 0.02, "humanoid-joystick", 122.8),
    "BerkeleyHumanoidJoystickRoughTerrain": RobotTask(12, 52, 114, 1000, 0.02, "humanoid-joystick", 109.2),
    "G1JoystickFlatTerrain": RobotTask(29, 103, 216, 1000, 0.02, "humanoid-joystick", 92.1),
    "G1JoystickRoughTerrain": RobotTask(29, 103, 216, 1000, 0.02, "humanoid-joystick", 81.7),
    "T1JoystickFlatTerrain": RobotTask(23, 85, 180, 1000, 0.02, "humanoid-joystick", 44.7),
    "T1JoystickRoughTerrain": RobotTask(23, 85, 180, 1000, 0.02, "humanoid-joystick", 36.2),
    "SpotFlatTerrainJoystick": RobotTask(12, 81, 167, 1000, 0.02, "locomotion", 52.6),
    "ApolloJoystickFlatTerrain": RobotTask(32, 112, 224, 1000, 0.02, "humanoid-joystick", 262.3),
    # Manipulation: a LEAP hand turning a cube, a Franka Panda arm picking one up, ALOHA's arms.
    "LeapCubeReorient": RobotTask(16, 57, 128, 1000, 0.05, "leap-cube-reorient", 73.8),
    "LeapCubeRotateZAxis": RobotTask(16, 32, 105, 500, 0.05, "leap-cube-rotate-z", 74.0),
    "PandaPickCube": RobotTask(8, 66, 0, 150, 0.02, "panda-pick-cube", 46.7),
    "PandaPickCubeOrientation": RobotTask(8, 66, 0, 150, 0.02, "panda-pick-cube", 45.7),
    "PandaPickCubeCartesian": RobotTask(3, 70, 0, 200, 0.05, "panda-pick-cube-cartesian", 44.7),
    "PandaOpenCabinet": RobotTask(8, 55, 0, 150, 0.02, "panda-open-cabinet", 45.0),
    "AlohaHandOver": RobotTask(14, 83, 0, 250, 0.02, "aloha-hand-over", 68.1),
}  # fmt: skip


def task_of(name: str) -> str | None:
    """The task a robot's name trains on, on either path and whatever its options
    ('mjx-robot/Go1JoystickFlatTerrain?noise_level=0' -> 'Go1JoystickFlatTerrain'); None for another name."""
    for prefix in (PREFIX, MJX_PREFIX):
        if name.startswith(prefix):
            task = name.removeprefix(prefix).partition("?")[0]
            return task if task in TASKS else None
    return None


def preset_of(name: str) -> str | None:
    """The preset of Playground's config for the robot that `name` trains (`task_of`); None for another name."""
    task = task_of(name)
    return TASKS[task].preset if task else None


def preset_mismatch(preset: str, name: str) -> str | None:
    """Why `preset`, where it is one of the robots' (or its CPU-sized variant), was not made for
    what `name` trains; None where it was, or where it is no robot's preset."""
    base = preset.removesuffix("-cpu")
    made_for = [task for task, facts in TASKS.items() if facts.preset == base]
    task = task_of(name)
    if not made_for or task in made_for:
        return None
    return f"--preset {preset} is Playground's config for {', '.join(made_for)}, not {name}"


def spec(task: str, name: str, backend: str) -> EnvSpec:
    """The spec of `task` under `name`: the policy reads `state`, the critic `privileged_state`
    (a flat task's one observation both)."""
    from rpo_jax.envs.protocol import EnvSpec

    facts = TASKS[task]
    keys: tuple[tuple[str, int], ...] = ()
    if facts.privileged_size:
        keys = (("state", facts.state_size), ("privileged_state", facts.privileged_size))
    size = facts.state_size + facts.privileged_size
    low, high = (-1.0,) * facts.action_size, (1.0,) * facts.action_size  # every task's action space
    policy_key, critic_key = ("state", "privileged_state") if keys else ("", "")
    return EnvSpec(name, size, facts.action_size, low, high, facts.episode_steps, backend, keys, policy_key, critic_key)


def parse_options(name: str, query: str) -> dict[str, Any]:
    """The options of a robot's name, the part after '?': 'noise_level=0,push_enable=false' ->
    {'noise_level': 0, 'push_enable': False} (numbers, true/false, or text); a key given twice is
    refused."""
    options: dict[str, Any] = {}
    for part in filter(None, query.split(",")):
        key, equals, value = part.partition("=")
        if not equals or not key.strip():
            raise UsageError(f"env {name!r}: an option is KEY=VALUE, got {part!r}")
        if key.strip() in options:
            raise UsageError(f"env {name!r}: option {key.strip()} is given twice")
        options[key.strip()] = _value(value.strip())
    return options


# Settings that must be positive (a step's length, a gain, a history), those that must not be
# negative (noise, damping, pushes' timing and size, thresholds), and probabilities, by name.
POSITIVE = ("ctrl_dt", "sim_dt", "kp", "action_scale", "history_len")
NOT_NEGATIVE = ("noise", "kd", "push_interval", "push_magnitude", "max_", "success_threshold", "box_init_range")
PROBABILITIES = ("_prob", "ema_alpha")


def check_option(name: str, key: str, value: Any, default: Any) -> None:
    """Refuses, in one line naming the option, a value of another type than the setting's
    (`default`: the task's own value) or outside its range."""
    kind = "true or false" if isinstance(default, bool) else "an integer" if isinstance(default, int) else "a number"
    numeric = not isinstance(default, (bool, str))
    integral = isinstance(default, int) and not isinstance(default, bool)
    if isinstance(default, bool) != isinstance(value, bool) or (
        numeric and (isinstance(value, str) or (integral and isinstance(value, float)))
    ):
        raise UsageError(f"env {name!r}: option {key} is {kind} (the task's is {default!r}), got {value!r}")
    if isinstance(value, bool) or isinstance(value, str):
        return
    if not math.isfinite(value):
        raise UsageError(f"env {name!r}: option {key} must be a finite number, got {value!r}")
    if key.endswith(POSITIVE) and not value > 0:
        raise UsageError(f"env {name!r}: option {key} must be > 0 (the task's is {default!r}), got {value!r}")
    if key.startswith(NOT_NEGATIVE) and value < 0:
        raise UsageError(f"env {name!r}: option {key} must be >= 0 (the task's is {default!r}), got {value!r}")
    if key.endswith(PROBABILITIES) and not 0 <= value <= 1:
        raise UsageError(f"env {name!r}: option {key} is a probability in [0, 1], got {value!r}")


def with_options(name: str, options: dict[str, Any]) -> str:
    """`name` with `options` among those after its '?', replacing any it gives under the same key:
    ('robot/Go1JoystickFlatTerrain', {'noise_level': 0}) -> 'robot/Go1JoystickFlatTerrain?noise_level=0'."""
    base, _, query = name.partition("?")
    merged = parse_options(name, query) | options
    text = ",".join(f"{key}={str(value).lower() if isinstance(value, bool) else value}" for key, value in merged.items())
    return base + ("?" + text if text else "")


def _value(text: str) -> Any:
    if text.lower() in ("true", "false"):
        return text.lower() == "true"
    if not text:
        return text
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text
