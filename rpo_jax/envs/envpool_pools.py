"""envpool's pools on the host, for every suite it steps (DeepMind Control, `rpo_jax.envs.dmc`;
MuJoCo Playground's robots, `rpo_jax.envs.robots`): how many threads a pool gets and where, and
the pool itself behind `rpo_jax.envs.host`'s `HostSimulators`."""

from __future__ import annotations

import functools
import os
from typing import Any, Mapping, Sequence

import jax
import numpy as np

from rpo_jax.errors import UsageError


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


def available_megabytes() -> float | None:
    """The memory the system can give new processes without swapping (Linux's MemAvailable), in
    MB; None where it cannot say."""
    try:
        with open("/proc/meminfo") as meminfo:
            fields = dict(line.split(":", 1) for line in meminfo)
        return int(fields["MemAvailable"].split()[0]) / 1000
    except (OSError, KeyError, ValueError):
        return None


def check_memory(task_id: str, num_envs: int, megabytes_each: float) -> None:
    """Refuses, in one line with the largest count that fits, `num_envs` simulators of
    `megabytes_each` (measured) that the available memory would not hold, before any is built:
    the kernel would kill the process without a word."""
    available = available_megabytes()
    if not megabytes_each or available is None or num_envs * megabytes_each <= 0.9 * available:
        return
    fits = int(0.9 * available // megabytes_each)
    raise UsageError(
        f"{task_id}: {num_envs:,} simulators need about {num_envs * megabytes_each / 1000:.1f} GB "
        f"({megabytes_each:g} MB each) and {available / 1000:.1f} GB is available: at most {fits:,} fit; "
        "give fewer environments (--num-envs, --num-seeds, --eval-episodes)"
    )


class EnvpoolSimulators:
    """One envpool pool of `num_envs` copies of a task (envpool's id `task_id`, e.g.
    'WalkerWalk-v1'), auto-reset within the step, its observation the concatenation of the
    arrays `obs_keys` names, in that order. `options`: the task's own settings (envpool's config
    fields, e.g. a robot's `noise_level`). `megabytes_each`: one simulator's resident memory,
    where measured, weighed against the machine's before the pool is built (`check_memory`).
    `metric_keys`: scalar fields of envpool's result that each step returns after its five arrays
    (a robot's reward terms: `HostEnv.task_metrics`).

    Steps and resets go through envpool's own `_send`, `_reset` and `_recv`, the calls under its
    public `send`, `reset` and `recv`, which rebuild the action's list and the result's named
    tuples at every step: on a cheap task that is a third of the step (benchmarks/lab/notes/host-side.md,
    "The host step's own overhead"). tests/test_dmc.py checks this path against the public one
    across an episode's end, for the envpool releases that pyproject.toml allows.

    An episode's last step is a truncation where envpool flags it (`trunc`: the time limit) and a
    termination otherwise: DeepMind Control's time limit keeps discount 1, but envpool's ports of
    MuJoCo Playground's tasks give discount 0 at theirs."""

    def __init__(
        self, task_id: str, action_size: int, obs_keys: Sequence[str], num_envs: int, seed: int,
        options: Mapping[str, Any] | None = None, megabytes_each: float = 0.0, metric_keys: Sequence[str] = (),
    ) -> None:  # fmt: skip
        import envpool

        check_memory(task_id, num_envs, megabytes_each)

        self.env_ids = np.arange(num_envs)
        threads = pool_threads(num_envs)
        affinity = pool_affinity(threads)
        # envpool seeds env i with seed + i.
        self.pool = envpool.make_dm(
            task_id, num_envs=num_envs, num_threads=threads, thread_affinity_offset=affinity, seed=seed, **(options or {})
        )
        # The layouts of the lists of arrays that `_send` takes and `_recv` gives, read once.
        self.action_parts = self.pool._from(np.zeros((num_envs, action_size)), self.env_ids)
        self.action_index = len(self.action_parts) - 1  # the action comes last, after the env ids
        where = {name: index for index, name in enumerate(self.pool._state_keys)}
        self.result_index = [where[f"obs:{key}"] for key in obs_keys]
        self.metric_index = [where[f"info:{key}"] for key in metric_keys]
        self.env_id_index, self.reward_index = where["info:env_id"], where["reward"]
        self.truncated_index, self.step_type_index = where["trunc"], where["step_type"]

    def _received(self) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
        """(env ids, observations [n, obs] in `obs_keys`' order, all arrays) of envpool's
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
        reward, time_limit = state[self.reward_index], state[self.truncated_index]
        step_type = state[self.step_type_index]
        metrics = [state[index] for index in self.metric_index]
        if not np.array_equal(env_id, self.env_ids):  # a pool stepped whole answers in order
            order = np.argsort(env_id)
            reached, step_type, time_limit, reward = reached[order], step_type[order], time_limit[order], reward[order]
            metrics = [metric[order] for metric in metrics]
        last = step_type == 2  # dm_env.StepType.LAST
        obs = reached.copy()
        if last.any():
            # Reset now rather than on envpool's next step, so the next action is taken in the
            # new episode, as the protocol's auto-reset requires.
            self.pool._reset(np.flatnonzero(last))
            fresh_id, fresh, _ = self._received()
            obs[fresh_id] = fresh
        # Copies: envpool may reuse the arrays it handed out.
        return obs, reward.copy(), last & ~time_limit, last & time_limit, reached, *(metric.copy() for metric in metrics)

    def close(self) -> None:
        self.pool.close()


class DrawnEnvpoolTask:
    """One copy of a task (envpool's id `task_id`, its observation the arrays `obs_keys` names,
    `options` its settings) drawn by envpool's own MuJoCo renderer from camera `camera_id` (-1:
    MuJoCo's free camera), `fps` steps a second of simulated time (`host.DrawnSimulator`), in the
    calling thread."""

    def __init__(
        self, task_id: str, obs_keys: Sequence[str], seed: int, width: int, height: int, fps: float,
        options: Mapping[str, Any] | None = None, camera_id: int = 0,
    ) -> None:  # fmt: skip
        import envpool

        gl_context().make_current()
        self.keys, self.fps, self.env_ids = list(obs_keys), fps, np.zeros(1, int)
        self.pool = envpool.make_dm(
            task_id, num_envs=1, num_threads=1, seed=seed, render_mode="rgb_array", render_width=width,
            render_height=height, render_camera_id=camera_id, **(options or {}),
        )  # fmt: skip

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


@functools.cache
def gl_context() -> Any:
    """An OpenGL context of the installed MuJoCo's, kept for the process's life, which envpool's
    MuJoCo draws with where it is current: without one, once a pool has been built, envpool
    finds no OpenGL ("gladLoadGL error", and the process exits). Its backend is MUJOCO_GL's
    (`rpo_jax.envs` chose EGL where no display is)."""
    import mujoco

    return mujoco.GLContext(8, 8)
