"""Wall time of training K vmapped seeds against one seed, measured in one process.

    python benchmarks/seeds.py --env cartpole --preset paper --seeds 10 --total-timesteps 204800

Both programs are compiled ahead of time, then each is timed (best of --repeats) on the same
config; the ratio K-seed time / 1-seed time is the cost of the sweep relative to one run. The
seeds are mapped as the trainer maps runs (`devices.map_runs`): one seed unbatched, K vmapped.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path
from typing import Any

from rpo_jax.config import Config
from rpo_jax.envs.recipes import PRESETS

# JAX and the environments are imported where they are used, so that --help answers at once.


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="cartpole", help="registered environment name (python -m rpo_jax.envs lists them)")
    parser.add_argument("--preset", choices=sorted(PRESETS), help="config of the training (default: the CPU config, Config())")
    parser.add_argument("--seeds", type=int, default=10, help="seeds of the vmapped program, timed against one seed")
    parser.add_argument("--total-timesteps", type=int, default=204_800, help="environment steps per seed")
    parser.add_argument("--num-envs", type=int, help="environments per seed (default: the preset's)")
    parser.add_argument("--repeats", type=int, default=2, help="timed calls of each program; the fastest counts")
    parser.add_argument("--json", type=Path, help="write the results here")
    return parser.parse_args(argv)


def timed_training(config: Config, env: Any, num_seeds: int, repeats: int) -> float:
    import jax

    from rpo_jax import ppo
    from rpo_jax.parallel import devices

    train = ppo.make_train(config, env)
    keys = jax.random.split(jax.random.PRNGKey(0), num_seeds)
    compiled = jax.jit(devices.map_runs(train)).lower(keys).compile()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(compiled(keys))
        times.append(time.perf_counter() - start)
    return min(times)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    import jax

    from rpo_jax import envs

    config = PRESETS[args.preset] if args.preset else Config()
    config = dataclasses.replace(config, total_timesteps=args.total_timesteps, rpo_alpha=0.5)
    if args.num_envs:
        config = dataclasses.replace(config, num_envs=args.num_envs)
    env = envs.make_env(args.env)
    one = timed_training(config, env, 1, args.repeats)
    many = timed_training(config, env, args.seeds, args.repeats)
    device = jax.devices()[0]
    result = {
        "env": args.env,
        "preset": args.preset or "default",
        "num_envs": config.num_envs,
        "total_timesteps": config.num_updates * config.batch_size,
        "seconds_1_seed": one,
        f"seconds_{args.seeds}_seeds": many,
        "ratio": many / one,
        "device": f"{device.platform}:{device.device_kind}",
    }
    print(json.dumps(result, indent=2))
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
