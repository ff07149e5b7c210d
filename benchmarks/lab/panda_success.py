"""What a trained Panda pick-cube policy does, by the task's own reward terms: the share of
episodes in which the gripper reached the box, lifted it and brought it to the target.

envpool's port reports each step's reward terms beside the observation (`info:reward_*`,
Playground's `pick.py` metrics): `gripper_box` (reaching), `lifted` and `success` (the box within
`success_threshold` of the target, worth 2 a step). A run's deterministic policy acts through
`rpo_jax.load_policy` in a fresh pool, each episode to its 150 steps.

    python benchmarks/lab/panda_success.py RUN_DIR [--run N] [--episodes 64] [--seed 0]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax
import numpy as np

from rpo_jax import load_policy
from rpo_jax.envs.robots import parse_name
from rpo_jax.run.directory import RunDir

TERMS = ("gripper_box", "box_target", "lifted", "success")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--run", type=int, default=None)
    parser.add_argument("--episodes", type=int, default=64)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    import envpool

    env_name = RunDir(args.run_dir).read_config()["env"]
    task, options = parse_name(env_name)
    if not task.startswith("PandaPickCube"):
        print(f"error: {env_name} is not a Panda pick-cube task", file=sys.stderr)
        return 2
    policy = load_policy(args.run_dir, args.run)
    pool = envpool.make_dm(f"{task}-v1", num_envs=args.episodes, seed=args.seed, **options)
    ts = pool.reset()
    sums = {term: np.zeros(args.episodes) for term in TERMS}
    returns, lifted_steps = np.zeros(args.episodes), np.zeros(args.episodes)
    for _ in range(pool.spec.config.max_episode_steps):
        action = np.asarray(policy(np.asarray(ts.observation.state, np.float32), jax.random.PRNGKey(0), True))
        ts = pool.step(action, np.arange(args.episodes))
        returns += ts.reward
        for term in TERMS:
            sums[term] += np.asarray(getattr(ts.observation, f"reward_{term}"))
        lifted_steps += np.asarray(ts.observation.reward_lifted) > 0
        if ts.last().all():
            break
    success = sums["success"] > 0
    print(f"{env_name} ({args.run_dir}), deterministic policy, {args.episodes} episodes: return {returns.mean():.2f}")
    for term in TERMS:
        share = np.mean(sums[term] > 0)
        print(f"  {term:12s} summed over an episode: {sums[term].mean():8.2f} (episodes where > 0: {share:.0%})")
    print(f"  lifted at some step: {np.mean(lifted_steps > 0):.0%}; success at some step: {success.mean():.0%}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
