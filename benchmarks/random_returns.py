"""The mean return of uniformly random actions, the low end of the report's score ranges.

    python benchmarks/random_returns.py gym/Pendulum-v1 gym/BipedalWalker-v3 --episodes 32

Actions are drawn uniformly within the environment's bounds at every step; returns are the
environment's own rewards over one whole episode of each of `--episodes` parallel copies."""

from __future__ import annotations

import argparse
import json
from typing import Any

# JAX and the environments are imported where they are used, so that --help answers at once.


def random_returns(name: str, episodes: int, seed: int) -> Any:
    """The returns of `episodes` episodes of uniformly random actions, as a numpy array."""
    import jax
    import numpy as np

    from rpo_jax import envs
    from rpo_jax.evaluate import episode_returns

    env = envs.make_env(name)
    low, high = np.asarray(env.spec.action_low), np.asarray(env.spec.action_high)

    def uniform(obs: Any, key: Any, deterministic: bool) -> Any:
        return jax.random.uniform(key, obs.shape[:-1] + low.shape, minval=low, maxval=high)

    return episode_returns(env, uniform, episodes, jax.random.PRNGKey(seed), deterministic=False)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("envs", nargs="+", help="registered environment names, each measured")
    parser.add_argument("--episodes", type=int, default=32, help="episodes of each environment, run as parallel copies")
    parser.add_argument("--seed", type=int, default=0, help="seed of the environments' starts and the actions")
    args = parser.parse_args(argv)
    for name in args.envs:
        returns = random_returns(name, args.episodes, args.seed)
        print(json.dumps({"env": name, "episodes": args.episodes, "mean": float(returns.mean()), "std": float(returns.std())}))


if __name__ == "__main__":
    main()
