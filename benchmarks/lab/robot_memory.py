"""Resident memory per envpool simulator of each of Playground's robots (the `robot/` tasks):
a fresh process builds a pool of 8 simulators (the task's model and code loaded once), then one
of 40 (4, then 12 with --small, for the largest), and its resident memory grown by the second
pool over its size is one simulator's. The figures are `robot_tasks.RobotTask.megabytes`.

    python benchmarks/lab/robot_memory.py [--small] [TASK ...]
"""

from __future__ import annotations

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


def main(args: list[str]) -> None:
    sizes = ("4", "12") if "--small" in args else ("8", "40")
    for task in [arg for arg in args if arg != "--small"] or TASKS:
        result = subprocess.run([sys.executable, "-c", CHILD, task, *sizes], capture_output=True, text=True, timeout=600)
        if result.returncode:
            last = (result.stderr.strip().splitlines() or [f"exit code {result.returncode}"])[-1]
            print(f"{task}: failed: {last}", flush=True)
        else:
            print(f"{task}: {float(result.stdout):.1f} MB", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
