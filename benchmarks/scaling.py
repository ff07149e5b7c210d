"""Training steps/s against the number of devices, for both placements of rpo_jax.parallel.devices.

    python benchmarks/scaling.py --env cartpole --num-envs 4096 --runs 8 --json OUT.json
    python benchmarks/scaling.py --cpu-devices 4 --num-envs 256 --runs 4   # on a CPU

For each device count D in --devices (default 1, 2, 4, ... up to all local devices):
- runs: --runs runs (seeds) of --num-envs environments each, split over D devices;
- envs: one run of --num-envs environments, split over D devices (data parallel).
Each program does --updates updates of the `isaacgym` preset (rpo, alpha 0.5), compiled ahead
of time and timed best of --repeats; steps/s counts every run's environment steps.
--cpu-devices N makes the CPU N devices, as `rpo_jax.train --cpu-devices` does. They share its
cores: split runs train faster than on one (each device's program keeps about one core busy),
data parallel slower (its all-reduces cost more than a CPU run's steps).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="cartpole", help="registered environment name (python -m rpo_jax.envs lists them)")
    parser.add_argument("--num-envs", type=int, default=4096, help="environments of each run")
    parser.add_argument("--runs", type=int, default=8, help="runs (seeds) of the runs placement")
    parser.add_argument("--updates", type=int, default=10, help="PPO updates in each timed program")
    parser.add_argument("--repeats", type=int, default=2, help="timed calls of each program; the fastest counts")
    parser.add_argument("--devices", type=int, nargs="+", help="device counts; default 1, 2, 4, ... up to all")
    parser.add_argument("--cpu-devices", type=int, help="make the CPU this many devices (as rpo_jax.train)")
    parser.add_argument("--json", type=Path, help="write the results here")
    return parser.parse_args(argv)


def timed(placement, config, env, num_runs: int, updates: int, repeats: int) -> tuple[float, float]:
    """(best seconds of `updates` updates of every run, compile seconds)."""
    import jax

    from rpo_jax import ppo

    trainer = placement.make_trainer(config, env)
    keys = jax.vmap(jax.random.PRNGKey)(jax.numpy.arange(num_runs))
    hparams = jax.vmap(lambda _: ppo.Hyperparams.from_config(config))(jax.numpy.arange(num_runs))
    init = placement.init_program(trainer)
    state = jax.block_until_ready(init(keys, hparams))
    start = time.perf_counter()
    program = placement.chunk_program(trainer, updates, jax.eval_shape(init, keys, hparams))
    compile_seconds = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        state, _ = jax.block_until_ready(program(state))
        times.append(time.perf_counter() - start)
    return min(times), compile_seconds


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    import jax

    from rpo_jax import envs
    from rpo_jax.envs.recipes import PRESETS
    from rpo_jax.parallel import devices

    devices.split_cpu(args.cpu_devices)

    available = len(jax.local_devices())
    counts = args.devices or [2**i for i in range(available.bit_length()) if 2**i <= available]
    env = envs.make_env(args.env)
    config = dataclasses.replace(PRESETS["isaacgym"], num_envs=args.num_envs, rpo_alpha=0.5)
    config = dataclasses.replace(config, total_timesteps=config.batch_size * args.updates)
    rows = []
    for placement_name, num_runs in (("runs", args.runs), ("envs", 1)):
        for count in counts:
            placement = devices.make_placement(count, placement_name == "envs", num_runs, config)
            seconds, compile_seconds = timed(placement, config, env, num_runs, args.updates, args.repeats)
            steps = num_runs * args.updates * config.batch_size
            rows.append({
                "placement": placement_name, "devices": count, "runs": num_runs, "num_envs": config.num_envs,
                "sps": steps / seconds, "seconds": seconds, "compile_seconds": compile_seconds,
            })  # fmt: skip
            print(json.dumps(rows[-1]), flush=True)
    result = {
        "env": args.env, "preset": "isaacgym", "updates": args.updates, "device": jax.devices()[0].device_kind,
        "platform": jax.devices()[0].platform, "cpu_devices": args.cpu_devices, "rows": rows,
    }  # fmt: skip
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
