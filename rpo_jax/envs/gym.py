"""OpenAI Gym's tasks of the paper: `gym/Pendulum-v1` in JAX, so its whole training stays one
jitted program, and the spec of `gym/BipedalWalker-v3`, Gymnasium's Box2D task (no JAX port),
which the registry builds through `rpo_jax.envs.gymnasium` on the host. Gym's time limits (200
and 1600 steps) are truncations."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from rpo_jax.envs.protocol import EnvSpec, TimeStep, first_step

PENDULUM_SPEC = EnvSpec("gym/Pendulum-v1", 3, 1, (-2.0,), (2.0,), 200, "jax")
BIPEDAL_WALKER_SPEC = EnvSpec("gym/BipedalWalker-v3", 24, 4, (-1.0,) * 4, (1.0,) * 4, 1600, "host")
SPECS = {spec.name: spec for spec in (PENDULUM_SPEC, BIPEDAL_WALKER_SPEC)}


class PendulumState(NamedTuple):
    theta: jax.Array  # [] angle from upright, radians (not wrapped, as Gym keeps it)
    theta_dot: jax.Array  # [] angular velocity


class Pendulum:
    """Gym's Pendulum-v1 with Gymnasium's constants (g 10, m 1, l 1, dt 0.05, speed within 8):
    observation (cos th, sin th, th_dot), torque clipped to [-2, 2], reward -(th^2 + 0.1 th_dot^2
    + 0.001 u^2) with th wrapped to [-pi, pi), no termination; `wrappers.TimeLimit` truncates
    after 200 steps. Starts uniform in th in [-pi, pi], th_dot in [-1, 1]. Written here rather than
    taken from gymnax, whose releases cap JAX below the versions this project supports."""

    spec = PENDULUM_SPEC
    MAX_SPEED, MAX_TORQUE, DT, G, M, L = 8.0, 2.0, 0.05, 10.0, 1.0, 1.0

    def reset(self, key: jax.Array) -> tuple[PendulumState, TimeStep]:
        high = jnp.array([jnp.pi, 1.0])
        theta, theta_dot = jax.random.uniform(key, (2,), minval=-high, maxval=high)
        state = PendulumState(theta, theta_dot)
        return state, first_step(self.observe(state))

    def step(self, state: PendulumState, action: jax.Array) -> tuple[PendulumState, TimeStep]:
        u = jnp.clip(action[0], -self.MAX_TORQUE, self.MAX_TORQUE)
        wrapped = (state.theta + jnp.pi) % (2 * jnp.pi) - jnp.pi
        reward = -(wrapped**2 + 0.1 * state.theta_dot**2 + 0.001 * u**2)
        accel = 3 * self.G / (2 * self.L) * jnp.sin(state.theta) + 3.0 / (self.M * self.L**2) * u
        theta_dot = jnp.clip(state.theta_dot + accel * self.DT, -self.MAX_SPEED, self.MAX_SPEED)
        state = PendulumState(state.theta + theta_dot * self.DT, theta_dot)
        obs = self.observe(state)
        false = jnp.zeros((), bool)
        return state, TimeStep(obs, reward.astype(jnp.float32), false, false, obs)

    @staticmethod
    def observe(state: PendulumState) -> jax.Array:
        return jnp.stack([jnp.cos(state.theta), jnp.sin(state.theta), state.theta_dot]).astype(jnp.float32)
