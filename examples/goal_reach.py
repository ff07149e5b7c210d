"""A worked example: an environment of one's own, written in JAX against rpo_jax's protocol.

A point mass in the plane is pushed by a 2-D force towards a goal drawn at reset. From the
repository's root (the current directory is on Python's path under `python -m`):

    python -m rpo_jax.envs --check examples.goal_reach:make_env
    python -m rpo_jax.train --env examples.goal_reach:make_env --out runs/goal-reach
    python -m rpo_jax.evaluate runs/goal-reach

or, registered under a name of its own and trained through the same command line in this process:

    python examples/goal_reach.py --out runs/goal-reach-named [any rpo_jax.train flag]
"""

from __future__ import annotations

import sys
from typing import Sequence

import jax
import jax.numpy as jnp
from flax import struct

from rpo_jax import register_env
from rpo_jax.envs import EnvSpec, TimeStep, first_step

# What the trainer sizes its networks, clips actions and truncates episodes by; declared
# statically so that listing the registered name builds nothing.
SPEC = EnvSpec(
    name="goal-reach", observation_size=6, action_size=2, action_low=(-1.0, -1.0), action_high=(1.0, 1.0),
    max_episode_steps=100, backend="jax",
)  # fmt: skip


@struct.dataclass
class GoalReachState:
    """Everything a step needs: JAX carries it between steps, so it holds arrays only."""

    position: jax.Array  # [2]
    velocity: jax.Array  # [2]
    goal: jax.Array  # [2]


class GoalReach:
    """Observation (6): position, velocity, goal. Action (2): a force in [-1, 1]^2. Reward per
    step: minus the distance to the goal; reaching it (closer than 0.1) terminates the episode,
    which ends the penalties, so getting there fast pays. `rpo_jax.envs.TimeLimit`
    truncates episodes after `spec.max_episode_steps`: the environment itself never truncates."""

    spec = SPEC
    dt = 0.1
    damping = 0.9  # velocity kept per step
    goal_radius = 0.1

    def reset(self, key: jax.Array) -> tuple[GoalReachState, TimeStep]:
        # Everything random comes from `key`, so the same key gives the same episode.
        position_key, goal_key = jax.random.split(key)
        state = GoalReachState(
            position=jax.random.uniform(position_key, (2,), minval=-1.0, maxval=1.0),
            velocity=jnp.zeros(2),
            goal=jax.random.uniform(goal_key, (2,), minval=-1.0, maxval=1.0),
        )
        return state, first_step(self.observe(state))

    def step(self, state: GoalReachState, action: jax.Array) -> tuple[GoalReachState, TimeStep]:
        # jnp only, no Python branching on values: the step is traced by jax.jit and jax.vmap.
        force = jnp.clip(action, -1.0, 1.0)
        velocity = self.damping * state.velocity + self.dt * force
        state = state.replace(position=state.position + self.dt * velocity, velocity=velocity)
        distance = jnp.linalg.norm(state.position - state.goal)
        obs = self.observe(state)
        terminated = distance < self.goal_radius
        # final_obs is the observation this step reached; the trainer's auto-reset replaces `obs`.
        return state, TimeStep(obs, -distance, terminated, jnp.zeros((), bool), obs)

    @staticmethod
    def observe(state: GoalReachState) -> jax.Array:
        return jnp.concatenate([state.position, state.velocity, state.goal])


def make_env() -> GoalReach:
    """The factory that `--env examples.goal_reach:make_env` and `register_env` call."""
    return GoalReach()


def main(argv: Sequence[str] | None = None) -> int:
    """Registers the environment as "goal-reach", trains it by that name with rpo_jax.train's
    flags in `argv`, and evaluates the run that --out names."""
    from rpo_jax import evaluate, train

    argv = sys.argv[1:] if argv is None else list(argv)
    register_env(SPEC.name, make_env, SPEC, replace=True)
    status = train.main(["--env", SPEC.name, *argv])
    out = train.given_value(argv, "--out")
    if status != 0 or out is None:
        return status
    return evaluate.main([out])


if __name__ == "__main__":
    sys.exit(main())
