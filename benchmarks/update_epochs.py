"""Time of the minibatch epochs alone (`ppo.minibatch_epochs`), one seed against K seeds vmapped.

    python benchmarks/update_epochs.py --env dmc/pendulum-swingup --num-envs 8 --num-steps 256 --seeds 2 5 10 20

The batch comes from one real rollout of each seed; the epochs program is compiled ahead of time
for one seed and each count of seeds and timed (best of --repeats): how the update alone scales
with seeds, and what one more seed costs where many share the program.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import jax

from rpo_jax import devices, envs, loss, ppo
from rpo_jax.config import PRESETS


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="dmc/pendulum-swingup")
    parser.add_argument("--preset", default="paper", choices=sorted(PRESETS))
    parser.add_argument("--num-envs", type=int, default=8)
    parser.add_argument("--num-steps", type=int, default=256)
    parser.add_argument("--seeds", type=int, nargs="+", default=[5], help="counts of seeds set against one")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    config = dataclasses.replace(PRESETS[args.preset], num_envs=args.num_envs, num_steps=args.num_steps, rpo_alpha=0.5)
    config = dataclasses.replace(config, total_timesteps=config.batch_size)
    trainer = ppo.make_trainer(config, envs.make_env(args.env))
    counts = sorted({1, *args.seeds})
    state = jax.jit(jax.vmap(trainer.init))(jax.random.split(jax.random.PRNGKey(0), counts[-1]))

    def batch_of(s: ppo.TrainState) -> loss.Batch:
        traj = ppo.rollout(trainer, s.params, s.env_state, s.obs, s.key)[2]
        return ppo.make_batch(trainer, s.params, traj, s.value_stats)[0]

    def epochs(s: ppo.TrainState, batch: loss.Batch) -> tuple:
        return ppo.minibatch_epochs(trainer, s.hparams, s.params, s.opt_state, batch, s.key)

    batch = jax.jit(jax.vmap(batch_of))(state)
    best: dict[int, float] = {}  # seconds an update, by count of seeds; counts[0] is 1
    for seeds in counts:
        inputs = jax.tree.map(lambda x, n=seeds: x[:n], (state, batch))
        run = jax.jit(devices.map_runs(epochs)).lower(*inputs).compile()  # one seed unbatched, as the trainer
        jax.block_until_ready(run(*inputs))
        times = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            jax.block_until_ready(run(*inputs))
            times.append(time.perf_counter() - start)
        best[seeds] = min(times)
        print(f"{args.env}: {seeds} seed(s), minibatch epochs {best[seeds] * 1e3:.1f} ms per update, "
              f"{best[seeds] / seeds * 1e3:.1f} ms a seed ({best[seeds] / best[1]:.2f}x one seed's)")  # fmt: skip


if __name__ == "__main__":
    main()
