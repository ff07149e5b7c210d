"""What the checkpoints' checksums cost: a checkpoint save timed with and without them, in one process.

    python benchmarks/checkpoint_cost.py                                  # the default Cartpole state
    python benchmarks/checkpoint_cost.py --hidden-sizes 1024 1024 --num-seeds 4

The state is the one `rpo_jax.runner` checkpoints (every run's parameters, optimiser state,
environments, normalisers and keys), built for the config given. Saves with the checksums
(`Checkpointer.save` as training calls it) and without them (the SHA-256 of the arrays left out)
alternate, so that both meet the same disk and cache; the median of each is reported.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import statistics
import tempfile
import time
from pathlib import Path
from unittest import mock

import jax
import numpy as np

from rpo_jax import checkpoint, envs, ppo
from rpo_jax.config import SWEEPABLE, Config


def initial_state(config: Config, env_name: str, num_seeds: int) -> ppo.TrainState:
    """The batched training state of `num_seeds` runs, as a run checkpoints it."""
    trainer = ppo.make_trainer(config, envs.make_env(env_name))
    keys = jax.vmap(jax.random.PRNGKey)(np.arange(num_seeds))
    hparams = ppo.Hyperparams(**{name: np.full(num_seeds, getattr(config, name), np.float32) for name in SWEEPABLE})
    return jax.block_until_ready(jax.jit(jax.vmap(trainer.init))(keys, hparams))


def timed_saves(state: ppo.TrainState, repeats: int) -> dict[str, list[float]]:
    """Seconds per save, with and without the checksums, alternating."""
    seconds: dict[str, list[float]] = {"with": [], "without": []}
    with tempfile.TemporaryDirectory() as directory:
        saver = checkpoint.Checkpointer(Path(directory))
        saver.save(0, state, {"update": 0})  # orbax's first save sets itself up: not timed
        for update in range(1, 2 * repeats + 1):
            kind = "with" if update % 2 else "without"
            unsummed = mock.patch.object(checkpoint, "_state_checksums", lambda tree: {})
            start = time.perf_counter()
            with unsummed if kind == "without" else contextlib.nullcontext():
                saver.save(update, state, {"update": update})
            seconds[kind].append(time.perf_counter() - start)
        saver.close()
    return seconds


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="cartpole")
    parser.add_argument("--hidden-sizes", type=int, nargs="+", help="default: the config's (64 64)")
    parser.add_argument("--num-envs", type=int, help="default: the config's (64)")
    parser.add_argument("--num-seeds", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=10)
    args = parser.parse_args()
    config = Config()
    if args.hidden_sizes:
        config = dataclasses.replace(config, hidden_sizes=tuple(args.hidden_sizes))
    if args.num_envs:
        config = dataclasses.replace(config, num_envs=args.num_envs)
    state = initial_state(config, args.env, args.num_seeds)
    size = sum(leaf.nbytes for leaf in jax.tree.leaves(state))
    seconds = timed_saves(state, args.repeats)
    with_sums, without = statistics.median(seconds["with"]), statistics.median(seconds["without"])
    result = {
        "env": args.env, "hidden_sizes": list(config.hidden_sizes), "num_envs": config.num_envs,
        "num_seeds": args.num_seeds, "state_mb": round(size / 1e6, 2), "repeats": args.repeats,
        "save_seconds_with_checksums": round(with_sums, 4), "save_seconds_without": round(without, 4),
        "ratio": round(with_sums / without, 3), "device": jax.devices()[0].device_kind,
    }  # fmt: skip
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
