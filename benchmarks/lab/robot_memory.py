"""Memory per simulator of each of Playground's robots, on either path.

    python benchmarks/lab/robot_memory.py [--small] [TASK ...]        # robot/ (envpool)
    python benchmarks/lab/robot_memory.py --mjx [--state] [TASK ...]  # mjx-robot/ (MJX)

envpool: a fresh process builds a pool of 8 simulators (the task's model and code loaded once),
then one of 40 (4, then 12 with --small, for the largest), and its resident memory grown by the
second pool over its size is one simulator's. The figures are `robot_tasks.RobotTask.megabytes`.

MJX: the memory XLA plans for one update of the task's preset (arguments, outputs and
temporaries, less what outputs alias; `Compiled.memory_analysis`), compiled for 64 and 128
environments stepping 20 steps each: the difference over 64 is one environment's share (its
simulator state, the step's working arrays, its rollout of 20 steps); the total at 64 says what
the networks and the optimiser add. Compiled only (nothing runs), one task at a time. With
--state, no compile: one environment's state (its simulator's data, observation and the task's
own), the least an environment can take, from the shapes of its reset.
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys

from rpo_jax.envs.robot_tasks import TASKS

CHILD = """
import envpool, sys
def rss():
    return int(open('/proc/self/statm').read().split()[1]) * 4096 / 1e6
task, first_size, second_size = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
first = envpool.make_dm(task + '-v1', num_envs=first_size, num_threads=1)
before = rss()
second = envpool.make_dm(task + '-v1', num_envs=second_size, num_threads=1)
print((rss() - before) / second_size)
"""
MJX_SIZES = (64, 128)
UNROLL = 20  # steps per environment an update: Playground's unroll for the legged robots, twice the Panda's


def envpool_megabytes(args: list[str]) -> None:
    sizes = ("4", "12") if "--small" in args else ("8", "40")
    for task in [arg for arg in args if arg != "--small"] or TASKS:
        result = subprocess.run([sys.executable, "-c", CHILD, task, *sizes], capture_output=True, text=True, timeout=600)
        if result.returncode:
            last = (result.stderr.strip().splitlines() or [f"exit code {result.returncode}"])[-1]
            print(f"{task}: failed: {last}", flush=True)
        else:
            print(f"{task}: {float(result.stdout):.1f} MB", flush=True)


def update_megabytes(task: str, num_envs: int) -> tuple[float, float]:
    """The memory XLA plans for one update of `task`'s preset with `num_envs` MJX environments,
    and the seconds its compilation took."""
    import time

    import jax

    from rpo_jax import envs, ppo
    from rpo_jax.envs.recipes import PRESETS

    preset = PRESETS[TASKS[task].preset]
    config = dataclasses.replace(preset, num_envs=num_envs, num_steps=UNROLL, total_timesteps=num_envs * UNROLL)
    trainer = ppo.make_trainer(config, envs.make_env(f"mjx-robot/{task}"))
    state = jax.eval_shape(trainer.init, jax.random.PRNGKey(0))
    start = time.perf_counter()
    stats = jax.jit(trainer.update).lower(state).compile().memory_analysis()
    seconds = time.perf_counter() - start
    planned = stats.argument_size_in_bytes + stats.output_size_in_bytes + stats.temp_size_in_bytes
    return (planned - stats.alias_size_in_bytes) / 1e6, seconds


def state_megabytes(task: str) -> float:
    """One MJX environment's state after its reset, from its shapes (nothing compiled or run)."""
    import jax

    from rpo_jax import envs

    shapes = jax.eval_shape(envs.make_env(f"mjx-robot/{task}").reset, jax.random.PRNGKey(0))
    return sum(leaf.size * leaf.dtype.itemsize for leaf in jax.tree.leaves(shapes)) / 1e6


def mjx_megabytes(tasks: list[str], state_only: bool) -> None:
    from rpo_jax.envs.mjx_robots import MJX_TASKS

    for task in tasks or MJX_TASKS:
        if state_only:
            try:
                print(f"{task}: its state {state_megabytes(task) * 1000:.1f} kB an environment", flush=True)
            except Exception as error:  # a task that cannot be built here: said, and the others go on
                print(f"{task}: failed: {str(error).splitlines()[0]}", flush=True)
            continue
        (small, seconds), (large, _) = (update_megabytes(task, size) for size in MJX_SIZES)
        each = (large - small) / (MJX_SIZES[1] - MJX_SIZES[0])
        print(f"{task}: {each:.2f} MB an environment; {small:.0f} MB at {MJX_SIZES[0]}; compiled in {seconds:.1f} s", flush=True)


if __name__ == "__main__":
    arguments = sys.argv[1:]
    if "--mjx" in arguments:
        mjx_megabytes([arg for arg in arguments if arg not in ("--mjx", "--state")], "--state" in arguments)
    else:
        envpool_megabytes(arguments)
