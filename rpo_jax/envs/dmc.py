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

import functools
import os
from typing import Any

import jax
import numpy as np

from rpo_jax.envs.dmc_tasks import ACTION_BOUNDS, EPISODE_STEPS, TASKS
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


def usable_cores() -> int:
    """The cores this process may run on (fewer than the machine's under `taskset` or a cgroup's
    cpuset; the machine's where the platform cannot say)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def pool_threads(num_envs: int) -> int:
    """envpool's threads for a pool of `num_envs`: one per usable core where JAX's CPU is one
    device; where it is split into devices, whose programs run beside the pools, the pool's share
    of the cores (at least one). More threads than cores only adds switching. Split in two on 2
    cores, pools of one thread trained five pendulum-swingup seeds 5-9% faster (in turns and with
    the runs split), five walker-walk seeds 2-6% faster with the runs split and 3-5% slower in
    turns (`--split-epochs`, meant for tasks whose update is the cost; benchmarks/lab/notes/host-side.md, "A
    pool's share of the cores where the CPU is split")."""
    return max(1, min(num_envs, usable_cores() // len(jax.devices("cpu"))))


def pool_affinity(threads: int) -> int:
    """envpool's `thread_affinity_offset` for a pool of `threads` threads: 0 (thread i on core i)
    where the pool has a thread on every core of the machine and JAX's CPU is one device, else -1
    (the threads left to the OS). Left to the OS, a pool's threads can share one core for the
    life of the process: a walker-walk pool of 8 stepped at 11.6k steps/s in some processes and
    18.5k in others on 2 cores, pinned at 17.9-19.0k in every one. Not where the CPU is split
    into devices, whose programs run beside the pools: there pinned pools trained five seeds in
    turns 7% slower (benchmarks/lab/notes/host-side.md, "envpool's threads pinned to the cores")."""
    whole_machine = threads == usable_cores() == (os.cpu_count() or 1)
    return 0 if whole_machine and len(jax.devices("cpu")) == 1 else -1


class DmcSimulators:
    """One envpool pool of `num_envs` copies of a task, auto-reset within the step.

    Steps and resets go through envpool's own `_send`, `_reset` and `_recv`, the calls under its
    public `send`, `reset` and `recv`, which rebuild the action's list and the result's named
    tuples at every step: on a cheap task that is a third of the step (benchmarks/lab/notes/host-side.md,
    "The host step's own overhead"). tests/test_dmc.py checks this path against the public one
    across an episode's end, for the envpool releases that pyproject.toml allows."""

    def __init__(self, task: str, num_envs: int, seed: int) -> None:
        import envpool

        self.env_ids = np.arange(num_envs)
        threads = pool_threads(num_envs)
        affinity = pool_affinity(threads)
        # envpool seeds env i with seed + i.
        self.pool = envpool.make_dm(
            envpool_task_id(task), num_envs=num_envs, num_threads=threads, thread_affinity_offset=affinity, seed=seed
        )
        # The layouts of the lists of arrays that `_send` takes and `_recv` gives, read once.
        self.action_parts = self.pool._from(np.zeros((num_envs, TASKS[task][0])), self.env_ids)
        self.action_index = len(self.action_parts) - 1  # the action comes last, after the env ids
        where = {name: index for index, name in enumerate(self.pool._state_keys)}
        self.result_index = [where[f"obs:{key}"] for key, _ in TASKS[task][1]]
        self.env_id_index, self.reward_index = where["info:env_id"], where["reward"]
        self.discount_index, self.step_type_index = where["discount"], where["step_type"]

    def _received(self) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
        """(env ids, observations [n, obs] in dm_control's key order, all arrays) of envpool's
        next result, in the order envpool gives it."""
        state = self.pool._recv()
        env_id = state[self.env_id_index]
        obs = np.concatenate([state[index].reshape(len(env_id), -1) for index in self.result_index], axis=1)
        return env_id, obs, state

    def reset(self) -> np.ndarray:
        self.pool._reset(self.env_ids)
        env_id, obs, _ = self._received()
        return obs[np.argsort(env_id)]

    def step(self, action: np.ndarray) -> tuple[np.ndarray, ...]:
        self.send(action)
        return self.receive()

    def send(self, action: np.ndarray) -> None:
        """Starts a step on envpool's threads; `receive` collects it."""
        parts = list(self.action_parts)
        parts[self.action_index] = np.asarray(action, np.float64)
        self.pool._send(parts)

    def receive(self) -> tuple[np.ndarray, ...]:
        env_id, reached, state = self._received()
        reward, discount = state[self.reward_index], state[self.discount_index]
        step_type = state[self.step_type_index]
        if not np.array_equal(env_id, self.env_ids):  # a pool stepped whole answers in order
            order = np.argsort(env_id)
            reached, step_type, discount, reward = reached[order], step_type[order], discount[order], reward[order]
        last = step_type == 2  # dm_env.StepType.LAST
        obs = reached.copy()
        if last.any():
            # Reset now rather than on envpool's next step, so the next action is taken in the
            # new episode, as the protocol's auto-reset requires.
            self.pool._reset(np.flatnonzero(last))
            fresh_id, fresh, _ = self._received()
            obs[fresh_id] = fresh
        # A copy: envpool may reuse the array it handed out.
        return obs, reward.copy(), last & (discount == 0), last & (discount > 0), reached

    def close(self) -> None:
        self.pool.close()


@functools.cache
def gl_context() -> Any:
    """An OpenGL context of the installed MuJoCo's, kept for the process's life, which envpool's
    MuJoCo draws with where it is current: without one, once a pool has been built, envpool
    finds no OpenGL ("gladLoadGL error", and the process exits). Its backend is MUJOCO_GL's
    (`rpo_jax.envs` chose EGL where no display is)."""
    import mujoco

    return mujoco.GLContext(8, 8)


class DrawnDmcTask:
    """One task drawn by envpool's own MuJoCo renderer from the task's first camera
    (`host.DrawnSimulator`), in the calling thread."""

    def __init__(self, task: str, seed: int, width: int, height: int) -> None:
        import envpool

        gl_context().make_current()
        self.keys = [key for key, _ in TASKS[task][1]]
        self.pool = envpool.make_dm(
            envpool_task_id(task), num_envs=1, num_threads=1, seed=seed,
            render_mode="rgb_array", render_width=width, render_height=height, render_camera_id=0,
        )  # fmt: skip
        self.fps = 1.0 / CONTROL_SECONDS.get(task.split("-")[0], DEFAULT_CONTROL_SECONDS)
        self.env_ids = np.zeros(1, int)

    def _observe(self, observation: Any) -> np.ndarray:
        return np.concatenate([np.asarray(getattr(observation, key)).reshape(-1) for key in self.keys])

    def reset(self) -> np.ndarray:
        return self._observe(self.pool.reset(self.env_ids).observation)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool]:
        ts = self.pool.step(np.asarray(action, np.float64)[None], self.env_ids)
        last, discount = bool(ts.step_type[0] == 2), float(ts.discount[0])  # dm_env.StepType.LAST
        return self._observe(ts.observation), float(ts.reward[0]), last and discount == 0, last and discount > 0

    def frame(self) -> np.ndarray:
        gl_context().make_current()  # MuJoCo's renderers make theirs current meanwhile
        return self.pool.render()[0]

    def close(self) -> None:
        self.pool.close()


def make(task: str) -> HostEnv:
    try:
        import envpool  # noqa: F401
    except ImportError:
        raise MissingExtraError(f"dmc/{task}", "envpool", "dmc") from None
    return HostEnv(
        SPECS[f"dmc/{task}"], lambda num_envs, seed: DmcSimulators(task, num_envs, seed),
        lambda seed, width, height: DrawnDmcTask(task, seed, width, height),
    )  # fmt: skip
