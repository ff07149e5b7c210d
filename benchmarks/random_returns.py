"""The mean return of uniformly random actions, the low end of the report's score ranges.

    python benchmarks/random_returns.py gym/Pendulum-v1 gym/BipedalWalker-v3 --episodes 32

Actions are drawn uniformly within the environment's bounds at every step (`--action zero`: the
middle of the bounds at every step, a policy that does nothing); returns are the environment's
own rewards over one whole episode of each of `--episodes` parallel copies."""

from __future__ import annotations

import argparse
import json
from typing import Any

# JAX and the environments are imported where they are used, so that --help answers at once.


def random_returns(name: str, episodes: int, seed: int, action: str = "uniform") -> Any:
    """The returns of `episodes` episodes of uniformly random actions (`action="zero"`: of the
    bounds' middle), as a numpy array."""
    import jax
    import numpy as np

    from rpo_jax import envs
    from rpo_jax.evaluate import episode_returns

    env = envs.make_env(name)
    low, high = np.asarray(env.spec.action_low), np.asarray(env.spec.action_high)

    def act(obs: Any, key: Any, deterministic: bool) -> Any:
        if action == "zero":
            return jax.numpy.broadcast_to((low + high) / 2, obs.shape[:-1] + low.shape)
        return jax.random.uniform(key, obs.shape[:-1] + low.shape, minval=low, maxval=high)

    return episode_returns(env, act, episodes, jax.random.PRNGKey(seed), deterministic=False)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("envs", nargs="+", help="registered environment names, each measured")
    parser.add_argument("--episodes", type=int, default=32, help="episodes of each environment, run as parallel copies")
    parser.add_argument("--seed", type=int, default=0, help="seed of the environments' starts and the actions")
    parser.add_argument("--action", choices=("uniform", "zero"), default="uniform", help="uniform in the bounds, or their middle")
    args = parser.parse_args(argv)
    for name in args.envs:
        returns = random_returns(name, args.episodes, args.seed, args.action)
        row = {"env": name, "action": args.action, "episodes": args.episodes}
        print(json.dumps(row | {"mean": float(returns.mean()), "std": float(returns.std())}))


if __name__ == "__main__":
    main()
