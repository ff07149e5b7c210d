"""DeepMind Control (`dmc/<domain>-<task>`) stepped on the host by envpool's C++ port of the
suite, which runs real MuJoCo (linked into envpool) on a pool of threads.

Why envpool and not dm_control: dm_control 1.0.50, the newest release, does not run on the
MuJoCo 4 that rpo_jax pins (it indexes MjModel fields that 4.0 removed), and stepping it in
Python costs about as much per step as the physics. envpool bundles its own MuJoCo build, so it
is independent of the pinned `mujoco`. Its DMC tasks follow dm_control's models, rewards and
1000-step episodes; tests/test_dmc.py checks observation layouts and the returns of a fixed
action sequence against figures that benchmarks/dmc_reference.py took from dm_control.

envpool's XLA interface (FFI custom calls) would keep stepping inside the compiled program,
but its pools are fixed (and seeded) when they are built and named by a static attribute of the
call, so a program vmapped over runs cannot give each run its own pool seeded from its key. The
pools are therefore stepped through `rpo_jax.envs.host.HostEnv`'s callbacks.

Observations are flattened the way dm_control's wrappers do it: the task's observation keys in
dm_control's order (the order its `get_observation` fills the dict, listed in `TASKS`), each
flattened and concatenated. envpool reports a domain's union of keys for every task of the
domain (e.g. humanoid's `position` for humanoid-walk, quadruped's ball and target for
quadruped-walk); those extra keys are left out. Episodes end by truncation at 1000 steps
(discount 1 at the last step); a last step with discount 0 would be a termination.
"""

from __future__ import annotations


from rpo_jax.envs.dmc_tasks import ACTION_BOUNDS, EPISODE_STEPS, TASKS
from rpo_jax.envs.envpool_pools import DrawnEnvpoolTask, EnvpoolSimulators
from rpo_jax.envs.host import HostEnv
from rpo_jax.envs.protocol import EnvSpec, MissingExtraError


def _spec(task: str) -> EnvSpec:
    action_size, keys = TASKS[task]
    domain = task.split("-")[0]
    bounds = ACTION_BOUNDS.get(domain, 1.0)
    low, high = ((-bounds,) * action_size, (bounds,) * action_size) if isinstance(bounds, float) else bounds
    return EnvSpec(f"dmc/{task}", sum(size for _, size in keys), action_size, low, high, EPISODE_STEPS, "host")


SPECS = {f"dmc/{task}": _spec(task) for task in TASKS}
# Seconds per control step of dm_control's domains (as MuJoCo Playground's ports record them),
# for the frame rate of videos; the domains it does not port take DEFAULT_CONTROL_SECONDS.
CONTROL_SECONDS = {
    "acrobot": 0.01, "ball_in_cup": 0.02, "cartpole": 0.01, "cheetah": 0.01, "finger": 0.02, "fish": 0.04,
    "hopper": 0.02, "humanoid": 0.025, "pendulum": 0.02, "point_mass": 0.02, "reacher": 0.02, "swimmer": 0.03,
    "walker": 0.025,
}  # fmt: skip
DEFAULT_CONTROL_SECONDS = 0.02


def envpool_task_id(task: str) -> str:
    """envpool's id of a dm_control task: 'walker-walk' -> 'WalkerWalk-v1'."""
    camel = "".join(part[:1].upper() + part[1:] for part in task.replace("-", "_").split("_"))
    return f"{camel}-v1"


def simulators(task: str, num_envs: int, seed: int) -> EnvpoolSimulators:
    """A pool of `num_envs` copies of `task` ('walker-walk'), observations flattened as dm_control's."""
    return EnvpoolSimulators(envpool_task_id(task), TASKS[task][0], [key for key, _ in TASKS[task][1]], num_envs, seed)


def make(task: str) -> HostEnv:
    try:
        import envpool  # noqa: F401
    except ImportError:
        raise MissingExtraError(f"dmc/{task}", "envpool", "dmc") from None
    return HostEnv(
        SPECS[f"dmc/{task}"], lambda num_envs, seed: simulators(task, num_envs, seed),
        lambda seed, width, height: DrawnEnvpoolTask(
            envpool_task_id(task), [key for key, _ in TASKS[task][1]], seed, width, height,
            fps=1.0 / CONTROL_SECONDS.get(task.split("-")[0], DEFAULT_CONTROL_SECONDS),
        ),
    )  # fmt: skip
