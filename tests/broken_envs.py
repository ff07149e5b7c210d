"""Environments with planted faults, each of which `check_env` must report in one line."""

import jax
import jax.numpy as jnp
import numpy as np

from rpo_jax import envs


class BrokenJaxEnv:
    """Five faults: the spec's observation size (3) is not the arrays' (2); action_low has one
    value for two actions; the reward is an int; reset draws from numpy's global generator
    instead of its key; and the observation becomes NaN at the third step."""

    spec = envs.EnvSpec("broken", 3, 2, (-1.0,), (1.0, 1.0), 10, "jax")

    def reset(self, key):
        draw = lambda: np.random.uniform(-1, 1, 2).astype(np.float32)  # not from the key
        position = jax.pure_callback(draw, jax.ShapeDtypeStruct((2,), jnp.float32))
        state = (position, jnp.zeros((), jnp.int32))
        return state, envs.first_step(position)

    def step(self, state, action):
        position, elapsed = state
        position, elapsed = position + 0.1 * action, elapsed + 1
        obs = jnp.where(elapsed >= 3, jnp.nan, position)
        false = jnp.zeros((), bool)
        return (position, elapsed), envs.TimeStep(obs, jnp.ones((), jnp.int32), false, false, obs)


class EarlyTruncation:
    """Well formed, but it truncates every episode after one step while its spec says 10."""

    spec = envs.EnvSpec("early", 2, 1, (-1.0,), (1.0,), 10, "jax")

    def reset(self, key):
        return jnp.zeros(2), envs.first_step(jax.random.uniform(key, (2,)))

    def step(self, state, action):
        obs = state + action[0]
        return obs, envs.TimeStep(obs, -jnp.sum(obs**2), jnp.zeros((), bool), jnp.ones((), bool), obs)


class EndlessSimulators:
    """Host simulators that never end an episode, whatever max_episode_steps says."""

    def __init__(self, num_envs, seed):
        self.obs = np.random.default_rng(seed).normal(size=(num_envs, 2)).astype(np.float32)

    def reset(self):
        return self.obs

    def step(self, action):
        self.obs = self.obs + 0.01 * action
        false = np.zeros(len(self.obs), bool)
        return self.obs, -np.sum(self.obs**2, axis=1), false, false, self.obs

    def close(self):
        pass


def endless_host_env():
    """Two faults: its episodes outlive the spec's 5 steps, and its backend is "jax" though it is host-side."""
    return envs.HostEnv(envs.EnvSpec("endless", 2, 1, (-1.0,), (1.0,), 5, "jax"), EndlessSimulators)


def _split(*keys):
    """A point-mass task of 6 observations whose spec names the parts `keys`."""
    from point_mass import PointMass

    env = PointMass()
    env.spec = envs.EnvSpec("split", 6, 1, (-1.0,), (1.0,), 10, "jax", keys, keys[0][0], keys[-1][0])
    return env


def negative_part():
    return _split(("state", -2), ("privileged_state", 8))


def fractional_parts():
    return _split(("state", 3.5), ("privileged_state", 2.5))


def empty_part():
    return _split(("state", 0), ("privileged_state", 6))


def repeated_part():
    return _split(("state", 3), ("state", 3))
