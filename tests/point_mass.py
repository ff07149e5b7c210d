"""A tiny pure-JAX environment behind the same protocol, for tests of the trainer's mechanics:
it compiles several times faster than MJX Cartpole, and the trainer cannot tell them apart."""

import jax
import jax.numpy as jnp

from rpo_jax import envs


class PointMass:
    """A unit mass on a line pushed by a force in [-1, 1]; reward -position^2; the episode
    terminates beyond |position| > 2 and is truncated after 50 steps."""

    spec = envs.EnvSpec("point_mass", 2, 1, (-1.0,), (1.0,), 50, "jax")

    def reset(self, key):
        state = jax.random.uniform(key, (2,), minval=-1.0, maxval=1.0)
        false = jnp.zeros((), bool)
        return state, envs.TimeStep(state, jnp.zeros(()), false, false, state)

    def step(self, state, action):
        velocity = state[1] + 0.1 * jnp.clip(action[0], -1.0, 1.0)
        state = jnp.stack([state[0] + 0.1 * velocity, velocity])
        terminated = jnp.abs(state[0]) > 2.0
        return state, envs.TimeStep(state, -(state[0] ** 2), terminated, jnp.zeros((), bool), state)
