"""compare.py's whole runs in one process: the library's `train(key)`, its `init` and updates
called one by one, and the loop's `train(key)`, every program compiled first, in interleaved
rounds; the first round (each program's first call) shown apart from the median of the others.

    cd benchmarks && PYTHONPATH=..:. python first_call.py --num-envs 4096 --rounds 4
"""

from __future__ import annotations

import argparse
import statistics
from typing import Any, Callable

import jax

import purejaxrl_loop  # this folder's, on the path when run as a script
from compare import ENV, playground_env, rpo_config
from phases import interleaved
from rpo_jax import envs, ppo


def programs(num_envs: int, timesteps: int) -> dict[str, Callable[[], Any]]:
    """name -> a call of one whole run, its programs compiled ahead of time."""
    config = rpo_config(num_envs, timesteps)
    trainer = ppo.make_trainer(config, envs.make_env(ENV))
    key = jax.random.PRNGKey(0)
    train = jax.jit(trainer.train).lower(key).compile()
    init = jax.jit(trainer.init).lower(key).compile()
    update = jax.jit(trainer.update).lower(init(key)).compile()
    loop = purejaxrl_loop.make_loop(num_envs, timesteps, playground_env)
    loop_train = jax.jit(loop.train).lower(key).compile()

    def one_by_one() -> Any:
        state = init(key)
        for _ in range(config.num_updates):
            state, _ = update(state)
        return state

    return {"library train": lambda: train(key), "init and updates one by one": one_by_one, "loop train": lambda: loop_train(key)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num-envs", type=int, default=4096, help="environments")
    parser.add_argument("--timesteps", type=int, default=1048576, help="environment steps of each run")
    parser.add_argument("--rounds", type=int, default=4, help="interleaved rounds, the first one each program's first call")
    args = parser.parse_args()
    seconds = interleaved(programs(args.num_envs, args.timesteps), args.rounds, warm_up=False)
    print(f"{args.num_envs} environments, {args.timesteps} steps a run\n")
    print("| run | first call s | median of the later calls s | later calls |")
    print("|---|---|---|---|")
    for name, times in seconds.items():
        later = ", ".join(f"{t:.2f}" for t in times[1:])
        print(f"| {name} | {times[0]:.2f} | {statistics.median(times[1:]):.2f} | {later} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
