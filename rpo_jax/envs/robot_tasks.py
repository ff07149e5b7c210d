"""MuJoCo Playground's robots that rpo_jax registers, as static data, so that the registry and
the experiments name them without importing a simulator or JAX (`spec` imports it when called);
the options of their names, which both paths read (`robots`: envpool's ports on the host;
`mjx_robots`: MJX); and Playground's training recipes for them (`PRESETS`). Read from envpool
1.2.5's ports; tests/test_robots.py checks them against it."""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING, Any

from rpo_jax.config import TANH_NORMAL, Config
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
    preset: str  # rpo_jax's preset of Playground's PPO config for it (`PRESETS`)
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


def _playground(unroll_length: int, batch_size: int, **fields) -> Config:
    """One of MuJoCo Playground's Brax PPO configs (`locomotion_params`, `manipulation_params`) in
    rpo_jax's terms. Brax gathers batch_size x num_minibatches unrolls of `unroll_length` steps
    an update, num_envs at a time: num_steps is that many steps per environment, so a preset with
    fewer environments (the CPU's) keeps the samples per update. Brax's choices kept: its policy
    (`tanh-normal`: a squashed Gaussian whose scale the network outputs), constant learning rate,
    no reward normalisation, no value clipping, its value loss (vf_coef 0.5 of a halved squared
    error), SiLU (its swish), Adam's epsilon 1e-8, clip 0.3, a gradient clip only where the task's
    config sets one. Not reproduced: observation normalisation without a clip (kept at 10
    standard deviations), GAE cut at each unroll of `unroll_length` (rpo_jax's runs over num_steps)."""
    base = dict(
        lr=3e-4, lr_schedule="constant", gamma=0.97, ent_coef=1e-2, clip_coef=0.3, clip_value_loss=False,
        max_grad_norm=1.0, adam_eps=1e-8, activation="silu", normalize_reward=False, num_minibatches=32,
        update_epochs=4, num_envs=8192, dist=TANH_NORMAL,
    )  # fmt: skip
    base.update(fields)
    base["num_steps"] = unroll_length * batch_size * base["num_minibatches"] // base["num_envs"]
    return Config(**base)


# Playground's recipes, by the tasks they were tuned for (`RobotTask.preset`). Locomotion:
LEGGED = dict(hidden_sizes=(512, 256, 128))
PRESETS: dict[str, Config] = {}
PRESETS["go1-joystick"] = _playground(20, 256, total_timesteps=200_000_000, **LEGGED)
PRESETS["go1-getup"] = _playground(20, 256, total_timesteps=50_000_000, **LEGGED)
PRESETS["go1-handstand"] = _playground(20, 256, total_timesteps=100_000_000, **LEGGED)
PRESETS["humanoid-joystick"] = _playground(20, 256, total_timesteps=200_000_000, clip_coef=0.2, ent_coef=5e-3, **LEGGED)
PRESETS["locomotion"] = _playground(
    20, 256, total_timesteps=100_000_000, hidden_sizes=(128,) * 4, critic_hidden_sizes=(256,) * 5
)  # Playground's default, for its tasks without a tuned config (Spot)
# Manipulation. Brax clips no gradient on these but the Cartesian pick-up (max_grad_norm unset).
MANIPULATION = dict(num_envs=2048, update_epochs=8, critic_hidden_sizes=(256,) * 5, max_grad_norm=0.0)
PANDA_PICK_CUBE = dict(total_timesteps=20_000_000, lr=1e-3, ent_coef=2e-2, hidden_sizes=(32,) * 4, **MANIPULATION)
PRESETS["panda-pick-cube"] = _playground(10, 512, **PANDA_PICK_CUBE)
# The same on a CPU's envpool simulators: 64 of them (about 16k-24k steps/s on 2 cores, where 2,048
# would be no faster), each stepping 2,560 steps an update so that an update's 163,840 samples and
# its 32 minibatches x 8 epochs are Playground's.
PRESETS["panda-pick-cube-cpu"] = _playground(10, 512, **{**PANDA_PICK_CUBE, "num_envs": 64})
PRESETS["panda-open-cabinet"] = _playground(
    10, 512, total_timesteps=40_000_000, lr=1e-3, ent_coef=2e-2, hidden_sizes=(32,) * 4, **MANIPULATION
)
PRESETS["panda-pick-cube-cartesian"] = _playground(
    10, 256, total_timesteps=5_000_000, lr=5e-4, ent_coef=7.5e-3, num_minibatches=8, reward_scale=0.1,
    hidden_sizes=(256, 256), **{**MANIPULATION, "num_envs": 1024, "max_grad_norm": 1.0},
)  # fmt: skip
PRESETS["aloha-hand-over"] = _playground(
    15,
    512,
    total_timesteps=100_000_000,
    lr=1e-3,
    ent_coef=2e-2,
    hidden_sizes=(256,) * 3,
    **{**MANIPULATION, "max_grad_norm": 1.0},
)
PRESETS["leap-cube-reorient"] = _playground(40, 256, total_timesteps=200_000_000, gamma=0.99, **LEGGED)
PRESETS["leap-cube-rotate-z"] = _playground(40, 256, total_timesteps=100_000_000, **LEGGED)
