"""What one seed of a DeepMind Control task starts from, beside the others: the simulator pool
its key draws (the orientation of the pole at episode starts, and the return of random actions)
and its initial policy's mean actions. Written to ask whether `dmc/pendulum-swingup`'s seed 3,
which never swings up under PPO or RPO in the reference experiment, starts differently.

    PYTHONPATH=.. python seed_probe.py --seeds 1 2 3 4 5
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile

import numpy as np

TASK, ENVPOOL_ID, NUM_ENVS = "dmc/pendulum-swingup", "PendulumSwingup-v1", 8


def pool_seeds(seeds: list[int]) -> list[int]:
    """The envpool seed each run's key draws, recorded by wrapping the pool's constructor during
    one update of the experiment's layout (paper preset, 8 environments of 256 steps)."""
    from rpo_jax import train
    from rpo_jax.envs import dmc

    drawn, build = [], dmc.DmcSimulators.__init__

    def recorded(self, task: str, num_envs: int, seed: int) -> None:
        if num_envs == NUM_ENVS:
            drawn.append(seed)
        build(self, task, num_envs, seed)

    dmc.DmcSimulators.__init__ = recorded
    flags = ["--env", TASK, "--preset", "paper", "--num-seeds", str(len(seeds)), "--seed", str(seeds[0])]
    flags += ["--num-envs", str(NUM_ENVS), "--num-steps", "256", "--total-timesteps", "2048", "--quiet"]
    try:
        with tempfile.TemporaryDirectory() as tmp:
            train.main([*flags, "--no-compile-cache", "--out", f"{tmp}/run"])
    finally:
        dmc.DmcSimulators.__init__ = build
    return drawn[: len(seeds)]


def pool_starts(seed: int, episodes: int) -> tuple[np.ndarray, float]:
    """The pole's orientation at the starts of `episodes` episodes per environment, and the mean
    return of random actions (N(0, 1) clipped to the bounds) over them."""
    import envpool

    rng, pool = np.random.default_rng(seed), envpool.make_dm(ENVPOOL_ID, num_envs=NUM_ENVS, seed=seed)
    step, starts, returns = pool.reset(), [], []
    for _ in range(episodes):
        starts.append(step.observation.orientation[:, 0].copy())
        total = np.zeros(NUM_ENVS)
        while True:
            step = pool.step(np.clip(rng.normal(0, 1, (NUM_ENVS, 1)), -1, 1))
            total += step.reward
            if step.step_type[0] == 2:  # every environment ends at the 1000-step limit together
                break
        returns.extend(total)
        step = pool.step(np.zeros((NUM_ENVS, 1)))  # envpool's reset step
    return np.concatenate(starts), float(np.mean(returns))


def initial_mean_actions(seed: int) -> np.ndarray:
    """The initial policy's deterministic actions over a grid of angles and velocities."""
    import jax

    from rpo_jax import make_env, make_policy, make_trainer
    from rpo_jax.config import PRESETS

    config = dataclasses.replace(PRESETS["paper"], num_envs=NUM_ENVS, num_steps=256)
    trainer = make_trainer(config, make_env(TASK))
    angle, velocity = np.meshgrid(np.linspace(-np.pi, np.pi, 41), np.linspace(-6, 6, 25))
    obs = np.stack([np.cos(angle).ravel(), np.sin(angle).ravel(), velocity.ravel()], 1).astype(np.float32)
    policy = make_policy(trainer, trainer.init(jax.random.PRNGKey(seed)))
    return np.asarray(jax.vmap(policy)(obs))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5], help="the runs' seeds")
    parser.add_argument("--episodes", type=int, default=20, help="episodes per environment of each pool")
    args = parser.parse_args()
    for seed, drawn in zip(args.seeds, pool_seeds(args.seeds)):
        starts, random_return = pool_starts(drawn, args.episodes)
        actions = initial_mean_actions(seed)
        quartiles = ", ".join(f"{q:.2f}" for q in np.quantile(starts, [0.25, 0.5, 0.75]))
        print(
            f"seed {seed}: pool seed {drawn}, start orientation quartiles {quartiles}, random-action return "
            f"{random_return:.2f}, initial mean action |max| {np.abs(actions).max():.3f}"
        )


if __name__ == "__main__":
    main()
