"""Changed physics and sensing: an environment whose model, observations or actions differ from
the nominal ones, by values that may be traced, so that one compiled program steps a whole grid
of them (`rpo_jax.robustness`).

Model axes scale fields of an MJX model (a factor of 1 changes nothing, bit for bit); they apply
to environments simulated by MJX in the program (`cartpole`, `ballbalance`) and are refused, in
one line, where the task has no such physics (a factor of cartpole's zero damping would change
nothing). Sensing and acting axes wrap any environment inside the program:

    friction        every geom's sliding friction          where contacts are on
    joint-friction  every degree of freedom's frictionloss where some is non-zero
    mass            every body's mass and inertia
    gain            every actuator's strength (gain and bias: a position servo's stiffness too)
    damping         every degree of freedom's damping      where some is non-zero
    gravity         gravity
    obs-noise       Gaussian noise of this standard deviation on every observation (its own units)
    action-noise    Gaussian noise of this standard deviation on every action, then clipped to the bounds
    delay           control steps between the policy's action and the simulator's (0 to MAX_DELAY)
"""

from __future__ import annotations

import copy
from typing import Any, Callable

import jax
import jax.numpy as jnp
from flax import struct

from rpo_jax.envs.protocol import Env, TimeStep
from rpo_jax.errors import UsageError

MAX_DELAY = 8


def _scaled(field: str) -> Callable[[Any, jax.Array], dict[str, Any]]:
    return lambda model, factor: {field: getattr(model, field) * factor}


def _gain(model: Any, factor: jax.Array) -> dict[str, Any]:
    # force = gain * ctrl + bias0 + bias1 * length + bias2 * velocity: all of it scales.
    gain, bias = model.actuator_gainprm, model.actuator_biasprm
    return {"actuator_gainprm": gain.at[:, 0].multiply(factor), "actuator_biasprm": bias.at[:, :3].multiply(factor)}


def _friction(model: Any, factor: jax.Array) -> dict[str, Any]:
    return {"geom_friction": model.geom_friction.at[:, 0].multiply(factor)}


def _mass(model: Any, factor: jax.Array) -> dict[str, Any]:
    return {"body_mass": model.body_mass * factor, "body_inertia": model.body_inertia * factor}


def _gravity(model: Any, factor: jax.Array) -> dict[str, Any]:
    return {"opt": model.opt.replace(gravity=model.opt.gravity * factor)}


# name -> (what it changes in the model, the field that must be non-zero for it to change anything)
MODEL_AXES: dict[str, tuple[Callable[[Any, jax.Array], dict[str, Any]], str]] = {
    "friction": (_friction, "geom_friction"),
    "joint-friction": (_scaled("dof_frictionloss"), "dof_frictionloss"),
    "mass": (_mass, "body_mass"),
    "gain": (_gain, "actuator_gainprm"),
    "damping": (_scaled("dof_damping"), "dof_damping"),
    "gravity": (_gravity, "opt.gravity"),
}
SIGNAL_AXES = ("obs-noise", "action-noise", "delay")
AXES = (*MODEL_AXES, *SIGNAL_AXES)
# The value at which an axis changes nothing.
NOMINAL = {**{name: 1.0 for name in MODEL_AXES}, **{name: 0.0 for name in SIGNAL_AXES}}


def simulated_model(env: Env) -> Any | None:
    """The MJX model that `env` (or the environment it wraps) steps, if it is one."""
    while env is not None:
        model = getattr(env, "model", None)
        if model is not None and type(model).__name__ == "Model" and hasattr(model, "body_mass"):
            return model
        env = getattr(env, "env", None)
    return None


def check_axes(env: Env, axes: tuple[str, ...]) -> None:
    """Refuses (UsageError, one line) an unknown axis, or one that `env` cannot apply or that
    would change nothing in its model."""
    for axis in axes:
        if axis not in AXES:
            raise UsageError(f"unknown perturbation {axis!r}; the axes are {', '.join(AXES)}")
        if axis not in MODEL_AXES:
            continue
        model = simulated_model(env)
        if model is None:
            raise UsageError(
                f"{env.spec.name} is not simulated by MJX inside the program, so {axis} cannot change; "
                f"its axes are {', '.join(SIGNAL_AXES)}"
            )
        field = MODEL_AXES[axis][1]
        values = model.opt.gravity if field == "opt.gravity" else getattr(model, field)
        contacts_off = axis == "friction" and int(model.opt.disableflags) & 1 << 4  # mjDSBL_CONTACT
        if contacts_off or not bool(jnp.any(values != 0)):
            raise UsageError(f"{axis} changes nothing in {env.spec.name}: its model has no {field.split('.')[-1]} in use")


@struct.dataclass
class PerturbedState:
    inner: Any
    key: jax.Array
    actions: jax.Array  # [MAX_DELAY + 1, action_size] the latest actions, newest first


class Perturbed:
    """`env` with the perturbations `values` (axis -> value, possibly traced): its model's fields
    scaled, noise on what it observes and on what it is told to do, its actions delayed."""

    def __init__(self, env: Env, values: dict[str, jax.Array | float]) -> None:
        self.values = {name: values.get(name, NOMINAL[name]) for name in AXES}
        self.model_axes = [name for name in MODEL_AXES if name in values]
        self.env = with_model(env, self._changed) if self.model_axes else env
        self.spec = env.spec

    def _changed(self, model: Any) -> Any:
        for name in self.model_axes:
            model = model.replace(**MODEL_AXES[name][0](model, jnp.asarray(self.values[name], jnp.float32)))
        return model

    def reset(self, key: jax.Array) -> tuple[PerturbedState, TimeStep]:
        # The simulator gets `key` itself: at nominal values the episodes are the unperturbed ones.
        inner, ts = self.env.reset(key)
        noise_key, key = jax.random.split(jax.random.fold_in(key, 0x0B5E))
        actions = jnp.zeros((MAX_DELAY + 1, self.spec.action_size))
        return PerturbedState(inner, key, actions), self._observed(ts, noise_key)

    def step(self, state: PerturbedState, action: jax.Array) -> tuple[PerturbedState, TimeStep]:
        action_key, noise_key, key = jax.random.split(state.key, 3)
        noisy = action + self.values["action-noise"] * jax.random.normal(action_key, action.shape)
        low, high = jnp.asarray(self.spec.action_low), jnp.asarray(self.spec.action_high)
        actions = jnp.concatenate([jnp.clip(noisy, low, high)[None], state.actions[:-1]])
        delay = jnp.asarray(self.values["delay"]).astype(jnp.int32)
        inner, ts = self.env.step(state.inner, actions[delay])
        return PerturbedState(inner, key, actions), self._observed(ts, noise_key)

    def _observed(self, ts: TimeStep, key: jax.Array) -> TimeStep:
        noise = self.values["obs-noise"] * jax.random.normal(key, ts.obs.shape)
        return ts.replace(obs=ts.obs + noise, final_obs=ts.final_obs + noise)


def with_model(env: Env, change: Callable[[Any], Any]) -> Env:
    """A shallow copy of `env` (and of the wrappers down to its simulator) whose MJX model is
    `change(model)`; the original is untouched."""
    env = copy.copy(env)
    model = getattr(env, "model", None)
    if model is not None and simulated_model(env) is model:
        env.model = change(model)
        return env
    if getattr(env, "env", None) is None:
        raise UsageError(f"{env.spec.name} has no MJX model to perturb")
    env.env = with_model(env.env, change)
    return env
