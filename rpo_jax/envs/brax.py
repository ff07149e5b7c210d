"""Brax's own environments (`brax/<name>`), with Brax's usual 1000-step episodes. Brax is
imported when an environment is built; `SPECS` lists them without it."""

from __future__ import annotations

import copy
from typing import Any, Callable

import jax

from rpo_jax.envs.protocol import EnvSpec
from rpo_jax.envs.wrappers import DoneIsTermination

EPISODE_STEPS = 1000

# Observation size, action size and backend of Brax's physics tasks (not its `fast`, a
# stand-in with no physics system for Brax's own tests), so that listing them does not build
# their systems (minutes on a CPU); tests/test_registry.py checks them against the built
# environments.
BRAX_SPECS = {
    "ant": (27, 8, "generalized"), "halfcheetah": (17, 6, "generalized"),
    "hopper": (11, 3, "generalized"), "humanoid": (244, 17, "generalized"),
    "humanoidstandup": (244, 17, "generalized"), "inverted_double_pendulum": (8, 1, "generalized"),
    "inverted_pendulum": (4, 1, "generalized"), "pusher": (23, 7, "generalized"),
    "reacher": (11, 2, "generalized"), "swimmer": (8, 2, "generalized"), "walker2d": (17, 6, "generalized"),
}  # fmt: skip
BRAX_ENVS = tuple(BRAX_SPECS)


def _spec(name: str, observation_size: int, action_size: int, backend: str) -> EnvSpec:
    high = (1.0,) * action_size
    return EnvSpec(f"brax/{name}", observation_size, action_size, tuple(-h for h in high), high, EPISODE_STEPS, f"brax-{backend}")


SPECS = {f"brax/{name}": _spec(name, *facts) for name, facts in BRAX_SPECS.items()}


class _NumpyWithOldClip:
    """`jax.numpy`, whose `clip` also takes the `a_min` and `a_max` that JAX 0.10 removed: Brax
    0.14.2's fluid drag (`brax.fluid`, which Swimmer's viscosity uses) still passes `a_min`, and
    `brax/swimmer` raised a TypeError in every step."""

    def __getattr__(self, name: str) -> Any:
        return getattr(jax.numpy, name)

    @staticmethod
    def clip(arr: jax.Array, min: Any = None, max: Any = None, *, a_min: Any = None, a_max: Any = None) -> jax.Array:
        return jax.numpy.clip(arr, a_min if min is None else min, a_max if max is None else max)


NUMPY_WITH_OLD_CLIP = _NumpyWithOldClip()


class BraxEnv(DoneIsTermination):
    """One of Brax's own environments (`brax/<name>`), with Brax's usual 1000-step episodes."""

    def __init__(self, name: str, backend: str | None = None) -> None:
        from brax import envs as brax_envs
        from brax import fluid

        from rpo_jax.envs.mjx_support import models_on_this_process

        fluid.jp = NUMPY_WITH_OLD_CLIP

        kwargs = {"backend": backend} if backend else {}
        # Brax's observation_size resets the environment, which puts MJX data too.
        with models_on_this_process():
            self.env = brax_envs.get_environment(name, **kwargs)
            observation_size = int(self.env.observation_size)
        high = (1.0,) * self.env.action_size
        self.spec = EnvSpec(
            f"brax/{name}",
            observation_size,
            int(self.env.action_size),
            tuple(-h for h in high),
            high,
            EPISODE_STEPS,
            f"brax-{getattr(self.env, 'backend', backend or 'default')}",
        )
        self.mj_model, self.control_dt = self.env.sys.mj_model, float(self.env.dt)

    @staticmethod
    def qpos(state: Any) -> jax.Array:
        return state.pipeline_state.q

    @property
    def model(self) -> Any:
        """Brax's System, an MJX model with its pipelines' own fields (`protocol.SimulatesModel`;
        `perturbations.BRAX_MODEL_AXES` says which an axis scales)."""
        return self.env.sys

    def with_model(self, change: Callable[[Any], Any]) -> BraxEnv:
        """A copy whose Brax environment steps `change(model)`: its pipeline reads `sys`."""
        env, inner = copy.copy(self), copy.copy(self.env)
        inner.sys = change(self.env.sys)
        env.env = inner
        return env

    @staticmethod
    def pushed(state: Any, velocity: jax.Array) -> Any:
        """`state` with `velocity` added to its pipeline's joint velocities `qd`."""
        return state.replace(pipeline_state=state.pipeline_state.replace(qd=state.pipeline_state.qd + velocity))
