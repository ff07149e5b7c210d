"""How far an untrained policy's deterministic action is from doing nothing: Brax's PPO network at
Playground's Go1 joystick config against rpo_jax's at its `go1-joystick` preset.

    python benchmarks/lab/initial_actions.py --seeds 5

The mean |action| over 1,000 observations drawn from N(0, 1) (what a fresh normaliser hands on),
for each seed's initial parameters: Brax's tanh of its location head, rpo_jax's location clipped
to the bounds. It explains why the two trainers' first evaluations differ on a task where standing
still scores and a wrong step topples the robot (`../compare_robot.py`)."""

from __future__ import annotations

import argparse

TASK = "Go1JoystickFlatTerrain"
SAMPLES = 1000


def brax_actions(seed: int) -> float:
    import jax
    import jax.numpy as jnp
    from brax.training.acme import running_statistics
    from brax.training.agents.ppo import networks
    from mujoco_playground.config import locomotion_params

    sizes = {"state": (48,), "privileged_state": (123,)}
    network = networks.make_ppo_networks(
        sizes, 12, preprocess_observations_fn=running_statistics.normalize,
        **locomotion_params.brax_ppo_config(TASK).network_factory,
    )  # fmt: skip
    key = jax.random.PRNGKey(seed)
    obs = {name: jax.random.normal(key, (SAMPLES, *shape)) for name, shape in sizes.items()}
    normaliser = running_statistics.init_state({name: jax.ShapeDtypeStruct(shape, jnp.float32) for name, shape in sizes.items()})
    logits = network.policy_network.apply(normaliser, network.policy_network.init(key), obs)
    return float(jnp.abs(jnp.tanh(logits[:, :12])).mean())


def rpo_jax_actions(seed: int) -> float:
    import jax
    import jax.numpy as jnp

    from rpo_jax import envs, ppo
    from rpo_jax.envs.recipes import PRESETS

    spec = envs.env_spec("robot/" + TASK)
    actor, _ = ppo.make_networks(PRESETS["go1-joystick"], spec)
    key = jax.random.PRNGKey(seed)
    obs = jax.random.normal(key, (SAMPLES, spec.observation_size))
    loc, _ = actor.apply(actor.init(key, obs), obs)
    return float(jnp.abs(jnp.clip(loc, -1.0, 1.0)).mean())


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=5, help="initial parameters drawn from seeds 0..N-1")
    args = parser.parse_args(argv)
    for name, measure in (("brax", brax_actions), ("rpo_jax", rpo_jax_actions)):
        print(name, "mean |action| per seed:", ", ".join(f"{measure(seed):.4f}" for seed in range(args.seeds)))


if __name__ == "__main__":
    main()
