"""OpenAI Gym's tasks of the paper: `gym/Pendulum-v1` in JAX (gymnax's port), so its whole
training stays one jitted program, and the spec of `gym/BipedalWalker-v3`, Gymnasium's Box2D
task (no JAX port), which the registry builds through `rpo_jax.envs.gymnasium` on the host.
Gym's time limits (200 and 1600 steps) are truncations."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from rpo_jax.envs.protocol import EnvSpec, MissingExtraError, TimeStep, first_step

PENDULUM_SPEC = EnvSpec("gym/Pendulum-v1", 3, 1, (-2.0,), (2.0,), 200, "jax")
BIPEDAL_WALKER_SPEC = EnvSpec("gym/BipedalWalker-v3", 24, 4, (-1.0,) * 4, (1.0,) * 4, 1600, "host")
SPECS = {spec.name: spec for spec in (PENDULUM_SPEC, BIPEDAL_WALKER_SPEC)}


class Pendulum:
    """Gym's Pendulum-v1 as gymnax implements it: observation (cos th, sin th, th_dot), torque
    in [-2, 2], reward -(th^2 + 0.1 th_dot^2 + 0.001 u^2), no termination. gymnax's own `done`
    (its time limit) is dropped; `wrappers.TimeLimit` truncates after 200 steps instead."""

    spec = PENDULUM_SPEC

    def __init__(self) -> None:
        try:
            import gymnax
        except ImportError:
            raise MissingExtraError(self.spec.name, "gymnax", "gym") from None
        self.env, self.params = gymnax.make("Pendulum-v1")

    def reset(self, key: jax.Array) -> tuple[Any, TimeStep]:
        obs, state = self.env.reset_env(key, self.params)
        return state, first_step(obs)

    def step(self, state: Any, action: jax.Array) -> tuple[Any, TimeStep]:
        # Pendulum's dynamics draw no randomness; the key is only part of gymnax's signature.
        obs, state, reward, _, _ = self.env.step_env(jax.random.PRNGKey(0), state, action, self.params)
        false = jnp.zeros((), bool)
        return state, TimeStep(obs, reward.astype(jnp.float32), false, false, obs)
