"""A tiny pure-JAX environment behind the same protocol, for tests of the trainer's mechanics:
it compiles several times faster than MJX Cartpole, and the trainer cannot tell them apart. And
its host-side twin (`host_point_mass`), a few lines of numpy stepped through host callbacks, for
the tests of host-side environments, also by import path (tests.point_mass:host_point_mass)."""

import jax
import jax.numpy as jnp
import numpy as np

from rpo_jax import envs
from rpo_jax.envs.host import HostEnv, SequentialSimulators


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


# The host-side point mass's episode length and spec.
EPISODE = 5
SPEC = envs.EnvSpec("host_point_mass", 2, 1, (-1.0,), (1.0,), EPISODE, "host")


class PointMassSim:
    """A point mass on a line, one simulator in Gymnasium's reset/step style: the episode is
    truncated after EPISODE steps; reward -position^2."""

    def __init__(self, index: int, seed: int) -> None:
        self.rng = np.random.default_rng([seed, index])

    def reset(self) -> np.ndarray:
        self.state, self.t = self.rng.uniform(-1, 1, 2), 0
        return self.state.copy()

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool]:
        velocity = self.state[1] + 0.1 * float(action[0])
        self.state, self.t = np.array([self.state[0] + 0.1 * velocity, velocity]), self.t + 1
        return self.state.copy(), -(self.state[0] ** 2), False, self.t >= EPISODE


def host_point_mass() -> HostEnv:
    return HostEnv(
        SPEC,
        lambda num_envs, seed: SequentialSimulators(
            num_envs, seed, PointMassSim, lambda sim: sim.reset(), lambda sim, action: sim.step(action)
        ),
    )
