"""Where a CPU-path robot update's time goes: envpool's raw stepping against the update's phases.

    python benchmarks/lab/robot_rate.py --env robot/PandaPickCube --preset panda-pick-cube-cpu --rounds 3

The raw rate: the task's envpool pool of the preset's environments stepped from plain Python with
uniform random actions, one update's steps (num_envs x num_steps), no JAX. The phases, each a
program of its own called on the state after one update: the whole
update, the rollout (the policy's forward pass and the host step through the program's
callbacks), values and GAE, and the minibatch epochs (`phases.update_phases`). Interleaved rounds; medians and ranges.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # this folder: phases.py
from phases import interleaved, spread, update_phases  # noqa: E402

from rpo_jax import envs, ppo  # noqa: E402
from rpo_jax.envs.recipes import PRESETS  # noqa: E402


def raw_seconds(env: envs.HostEnv, num_envs: int, steps: int) -> float:
    """Seconds of `steps` steps of a fresh pool of `num_envs` simulators, random actions."""
    pool = env.make_simulators(num_envs, 0)
    rng = np.random.default_rng(0)
    low, high = np.asarray(env.spec.action_low), np.asarray(env.spec.action_high)
    actions = rng.uniform(low, high, (steps, num_envs, env.spec.action_size))
    try:
        pool.reset()
        start = time.perf_counter()
        for action in actions:
            pool.step(action)
        return time.perf_counter() - start
    finally:
        pool.close()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="robot/PandaPickCube")
    parser.add_argument("--preset", default="panda-pick-cube-cpu", choices=sorted(PRESETS))
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args(argv)
    config = PRESETS[args.preset]
    config = dataclasses.replace(config, total_timesteps=config.batch_size * 4)
    env = envs.make_env(args.env)
    samples = config.num_envs * config.num_steps
    raw = [raw_seconds(env, config.num_envs, config.num_steps) for _ in range(args.rounds)]
    times = {"envpool raw (Python)": raw, **interleaved(update_phases(ppo.make_trainer(config, env)), args.rounds)}
    whole = statistics.median(times["whole update"])
    print(f"{args.env}, preset {args.preset}: {config.num_envs} environments x {config.num_steps} steps = {samples:,} samples")
    print("| phase | seconds, median (range) | steps/s | share of the update |")
    print("|---|---|---|---|")
    for name, seconds in times.items():
        median = statistics.median(seconds)
        print(f"| {name} | {spread(seconds)} | {samples / median:,.0f} | {median / whole:.0%} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
