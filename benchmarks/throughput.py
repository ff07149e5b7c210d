"""Environment and training throughput of one environment, measured in one process.

    python benchmarks/throughput.py --env cartpole --num-envs 1024 --json OUT.json

env_sps: a jitted lax.scan of vmapped auto-resetting steps with uniform random actions, timed
after a warm-up call, from a state reset beforehand (for a host-side environment, the scan of
its callback steps). raw_sps (host-side environments only): the same steps on the host
simulators called directly from Python with numpy actions, no JAX involved; with --seeds K,
seeds_raw_sps is K such pools stepped side by side (with --shared-pools, one pool of K x
--num-envs, as the seeds then step), against which K seeds' training is set where the
simulators are the cost. train_sps: the full
PPO/RPO update (rollout, GAE, epochs of minibatch SGD) with --preset (default `isaacgym`) at
--num-envs, timed after compilation. compile_seconds: the ahead-of-time compilation of that
training program.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from rpo_jax.envs.recipes import PRESETS

if TYPE_CHECKING:
    from rpo_jax.envs.host import HostEnv

# JAX and the environments are imported where they are used, so that --help answers at once.


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="cartpole", help="registered environment name (python -m rpo_jax.envs lists them)")
    parser.add_argument("--num-envs", type=int, default=1024, help="parallel environments, in the stepping and the training")
    parser.add_argument("--preset", default="isaacgym", choices=sorted(PRESETS), help="config of the timed training")
    parser.add_argument("--num-steps", type=int, help="rollout length of the timed training (default: the preset's)")
    parser.add_argument("--env-steps", type=int, default=500, help="steps per environment in the raw stepping scan")
    parser.add_argument("--train-updates", type=int, default=20, help="PPO updates in the timed training program")
    parser.add_argument(
        "--seeds", type=int, default=1,
        help="also time this many seeds trained in one program; seeds_wall_ratio is its wall time over one seed's",
    )  # fmt: skip
    parser.add_argument(
        "--shared-pools", action="store_true", help="the seeds share one pool of host simulators, as with train --shared-pools"
    )
    parser.add_argument("--repeats", type=int, default=3, help="timed calls of each program; the fastest counts")
    parser.add_argument("--json", type=Path, help="write the results here")
    return parser.parse_args(argv)


def best_of(fn, repeats: int) -> float:
    """Fastest wall time of `fn()` over `repeats` calls (the least disturbed by other load)."""
    import jax

    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return min(times)


def env_steps_per_second(name: str, num_envs: int, num_steps: int, repeats: int) -> float:
    import jax
    import jax.numpy as jnp

    from rpo_jax import envs

    env = envs.make_vector_env(name, num_envs)
    low, high = jnp.asarray(env.spec.action_low), jnp.asarray(env.spec.action_high)

    @jax.jit
    def rollout(state, key):
        def step(state, key):
            action = jax.random.uniform(key, (num_envs, env.spec.action_size), minval=low, maxval=high)
            state, ts = env.step(state, action)
            return state, ts.reward.sum()

        state, rewards = jax.lax.scan(step, state, jax.random.split(key, num_steps))
        return state, rewards.sum()

    key = jax.random.PRNGKey(0)
    # Reset outside the timed scan: a host-side environment builds its simulators there.
    state, _ = jax.jit(env.reset)(key)
    jax.block_until_ready(rollout(state, key))  # compile and warm up
    return num_envs * num_steps / best_of(lambda: rollout(state, key), repeats)


def raw_host_steps_per_second(
    env: HostEnv, num_envs: int, num_steps: int, repeats: int, num_pools: int = 1
) -> tuple[float, float]:
    """Steps/s summed over `num_pools` pools of `num_envs` simulators, each seeded apart, stepped
    from Python with numpy actions as the trainer's callback steps its runs' pools (side by side),
    and the cores they kept busy: the process's CPU seconds over the wall seconds of all repeats."""
    import numpy as np

    from rpo_jax.envs.host import step_side_by_side

    pools = [env.make_simulators(num_envs, seed * num_envs) for seed in range(num_pools)]
    for pool in pools:
        pool.reset()
    spec = env.spec
    shape = (num_steps, num_pools, num_envs, spec.action_size)
    actions = np.random.default_rng(0).uniform(spec.action_low, spec.action_high, shape).astype(np.float32)

    def run() -> None:
        for action in actions:
            step_side_by_side(pools, action)

    wall, cpu = time.perf_counter(), time.process_time()
    try:
        sps = num_pools * num_envs * num_steps / best_of(run, repeats)
        return sps, (time.process_time() - cpu) / (time.perf_counter() - wall)
    finally:
        for pool in pools:
            pool.close()


def train_steps_per_second(
    name: str, preset: str, num_envs: int, num_steps: int | None, num_updates: int, repeats: int, num_seeds: int = 1,
    shared_pools: bool = False,
) -> tuple[float, float]:  # fmt: skip
    """Training steps/s summed over `num_seeds` seeds trained in one program (`devices.map_runs`:
    vmapped, and one seed unbatched, as `train --num-seeds` does), and the program's compile time."""
    import jax

    from rpo_jax import envs, ppo
    from rpo_jax.parallel import devices

    config = dataclasses.replace(PRESETS[preset], num_envs=num_envs, rpo_alpha=0.5)
    config = dataclasses.replace(config, num_steps=num_steps or config.num_steps)
    config = dataclasses.replace(config, total_timesteps=config.batch_size * num_updates)
    env = envs.make_env(name)
    trainer = ppo.make_trainer(config, env.sharing_pools() if shared_pools else env)
    keys = jax.random.split(jax.random.PRNGKey(0), num_seeds)
    state = jax.jit(devices.map_runs(trainer.init))(keys)
    start = time.perf_counter()
    run = jax.jit(devices.map_runs(lambda s: trainer.scan_updates(s, num_updates))).lower(state).compile()
    compile_seconds = time.perf_counter() - start
    jax.block_until_ready(run(state))  # warm-up
    steps = num_seeds * config.batch_size * num_updates
    return steps / best_of(lambda: run(state), repeats), compile_seconds


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    import jax

    from rpo_jax import envs
    from rpo_jax.envs.host import HostEnv

    try:
        env = envs.make_env(args.env)
    except ValueError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2

    raw_sps, raw_cores = (
        raw_host_steps_per_second(env, args.num_envs, args.env_steps, args.repeats) if isinstance(env, HostEnv) else (None, None)
    )
    env_sps = env_steps_per_second(args.env, args.num_envs, args.env_steps, args.repeats)
    training = (args.env, args.preset, args.num_envs, args.num_steps, args.train_updates, args.repeats)
    train_sps, compile_seconds = train_steps_per_second(*training)
    seeds_sps = train_steps_per_second(*training, args.seeds, args.shared_pools)[0] if args.seeds > 1 else None
    # Where the simulators are the cost, K seeds' training against the simulators they step, alone.
    pools, pool_envs = (1, args.seeds * args.num_envs) if args.shared_pools else (args.seeds, args.num_envs)
    seeds_raw_sps, seeds_raw_cores = (
        raw_host_steps_per_second(env, pool_envs, args.env_steps, args.repeats, pools) if seeds_sps and raw_sps else (None, None)
    )
    device = jax.devices()[0]
    result = {
        "env": args.env,
        "num_envs": args.num_envs,
        "preset": args.preset,
        "num_steps": args.num_steps,
        "raw_sps": raw_sps,
        "raw_cores": raw_cores,
        "env_sps": env_sps,
        "train_sps": train_sps,
        "train_to_env_ratio": train_sps / env_sps,
        "train_to_raw_ratio": train_sps / raw_sps if raw_sps else None,
        "compile_seconds": compile_seconds,
        "seeds": args.seeds,
        "shared_pools": args.shared_pools,
        "seeds_train_sps": seeds_sps,
        # The same steps per seed: K seeds' wall time over one seed's is K * (1-seed sps / K-seed sps).
        "seeds_wall_ratio": args.seeds * train_sps / seeds_sps if seeds_sps else None,
        "seeds_raw_sps": seeds_raw_sps,
        "seeds_raw_cores": seeds_raw_cores,
        "seeds_train_to_raw_ratio": seeds_sps / seeds_raw_sps if seeds_raw_sps else None,
        "device": f"{device.platform}:{device.device_kind}",
        "jax": jax.__version__,
    }
    report(result)
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    return 0


def report(result: dict) -> None:
    """Prints `result` as a table row and, with several seeds, a line for them."""
    raw = f"{result['raw_sps']:>14,.0f}" if result["raw_sps"] else f"{'-':>14}"
    print(f"{'env':<20}{'num_envs':>10}{'raw_sps':>14}{'env_sps':>14}{'train_sps':>14}{'compile_s':>11}  device")
    print(
        f"{result['env']:<20}{result['num_envs']:>10}{raw}{result['env_sps']:>14,.0f}{result['train_sps']:>14,.0f}"
        f"{result['compile_seconds']:>11.1f}  {result['device']}"
    )
    if result["raw_sps"]:
        print(
            f"one pool stepped alone kept {result['raw_cores']:.2f} cores busy; one seed trains at "
            f"{result['train_to_raw_ratio']:.2f}x its rate"
        )
    seeds, sps = result["seeds"], result["seeds_train_sps"]
    if sps:
        print(f"{seeds} seeds in one program: {sps:,.0f} steps/s, wall time {result['seeds_wall_ratio']:.2f}x one seed's")
    if result["seeds_raw_sps"]:
        apart = f"their {seeds} pools stepped alone, side by side"
        simulators = "their one shared pool stepped alone" if result["shared_pools"] else apart
        print(
            f"{simulators}: {result['seeds_raw_sps']:,.0f} steps/s on "
            f"{result['seeds_raw_cores']:.2f} cores; the {seeds} seeds train at {result['seeds_train_to_raw_ratio']:.2f}x it"
        )


if __name__ == "__main__":
    sys.exit(main())
