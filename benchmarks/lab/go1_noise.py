"""How much action noise Playground's Go1 survives: episodes of envpool's Go1 joystick port under
independent Gaussian actions of each scale, clipped to [-1, 1] as rpo_jax's policy acts.

    python benchmarks/lab/go1_noise.py --scales 0 0.1 0.135 0.3 0.6 1 --steps 600

For each scale: the falls (the task terminates an episode when the robot tips over) per 1,000
steps, and the reward a step. Zero actions hold the default pose and stand for the whole episode;
why the `go1-joystick` preset starts its policy at scale e^-2 (`../../docs/robots.md`)."""

from __future__ import annotations

import argparse

import numpy as np

TASK, ENVS = "Go1JoystickFlatTerrain-v1", 16


def survive(scale: float, steps: int, seed: int) -> dict[str, float]:
    import envpool

    pool = envpool.make(TASK, env_type="gymnasium", num_envs=ENVS, seed=seed)
    pool.reset()
    rng = np.random.default_rng(seed)
    falls, rewards = 0, 0.0
    for _ in range(steps):
        action = np.clip(rng.normal(0.0, scale, (ENVS, 12)), -1.0, 1.0)
        _, reward, terminated, _, _ = pool.step(action)
        falls += int(terminated.sum())
        rewards += float(reward.sum())
    pool.close()
    return {"falls": falls, "reward_a_step": rewards / (steps * ENVS)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scales", type=float, nargs="+", default=[0.0, 0.1, 0.135, 0.3, 0.6, 1.0])
    parser.add_argument("--steps", type=int, default=600, help="steps of each of the 16 environments")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    print("| action scale | falls per 1,000 steps | reward a step |")
    print("|---|---|---|")
    for scale in args.scales:
        found = survive(scale, args.steps, args.seed)
        print(f"| {scale} | {1000 * found['falls'] / (ENVS * args.steps):.1f} | {found['reward_a_step']:.5f} |")


if __name__ == "__main__":
    main()
