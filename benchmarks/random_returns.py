"""The mean return of uniformly random actions, the low end of the report's score ranges.

    python benchmarks/random_returns.py gym/Pendulum-v1 gym/BipedalWalker-v3 --episodes 32

Actions are drawn uniformly within the environment's bounds at every step; returns are the
environment's own rewards over one whole episode of each of `--episodes` parallel copies."""

from __future__ import annotations

import argparse
import json

import jax
import numpy as np

from rpo_jax import envs
from rpo_jax.evaluate import episode_returns


def random_returns(name: str, episodes: int, seed: int) -> np.ndarray:
    env = envs.make_env(name)
    low, high = np.asarray(env.spec.action_low), np.asarray(env.spec.action_high)

    def uniform(obs: jax.Array, key: jax.Array, deterministic: bool) -> jax.Array:
        return jax.random.uniform(key, obs.shape[:-1] + low.shape, minval=low, maxval=high)

    return episode_returns(env, uniform, episodes, jax.random.PRNGKey(seed), deterministic=False)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("envs", nargs="+")
    parser.add_argument("--episodes", type=int, default=32)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    for name in args.envs:
        returns = random_returns(name, args.episodes, args.seed)
        print(json.dumps({"env": name, "episodes": args.episodes, "mean": float(returns.mean()), "std": float(returns.std())}))


if __name__ == "__main__":
    main()
