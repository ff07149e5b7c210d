"""Changed physics and sensing: an environment whose model, observations or actions differ from
the nominal ones, by values that may be traced, so that one compiled program steps a whole grid
of them (`rpo_jax.robustness`).

Model axes scale fields of an MJX model (a factor of 1 changes nothing, bit for bit); they apply
to environments simulated in the program (`cartpole`, `ballbalance`, `mjx-dmc/`, `mjx-robot/`,
and Brax's `brax/`, whose System adds fields of its own: `protocol.SimulatesModel`) and, on the
host, to the MuJoCo models of Gymnasium's MuJoCo tasks (`scale_in_place`, `rpo_jax.robustness`);
they are refused, in one line, where the task has no such physics (a factor of cartpole's zero
damping would change nothing). Sensing and acting axes wrap any environment:

    friction        every geom's sliding friction          where contacts are on
    joint-friction  every degree of freedom's frictionloss where some is non-zero
    mass            every body's mass and inertia
    gain            every actuator's strength (gain and bias: a position servo's stiffness too)
    damping         every degree of freedom's damping      where some is non-zero
    gravity         gravity
    push            a kick of this speed (m/s) to the first joint, about once every PUSH_EVERY_S seconds
    obs-noise       Gaussian noise of this standard deviation on every observation (its own units)
    action-noise    Gaussian noise of this standard deviation on every action, then clipped to the bounds
    delay           control steps between the policy's action and the simulator's (0 to MAX_DELAY)
"""

from __future__ import annotations

import copy
import dataclasses
import math
from typing import Any, Callable

import jax
import jax.numpy as jnp
from flax import struct

from rpo_jax.envs.protocol import Env, SimulatesModel, TimeStep
from rpo_jax.errors import UsageError

MAX_DELAY = 8
# A task's name, then its perturbations drawn per episode: `cartpole+mass=0.8:1.2+obs-noise=0:0.05`.
SEPARATOR = "+"


# name -> the model fields it scales, each (field, index) (a dotted field is a field's field:
# "opt.gravity"); the first is the field that must be non-zero somewhere for the axis to change
# anything.
ALL, FIRST = (slice(None),), (slice(None), 0)
MODEL_AXES: dict[str, tuple[tuple[str, tuple], ...]] = {
    "friction": (("geom_friction", FIRST),),  # the sliding coefficient, not torsion or rolling
    "joint-friction": (("dof_frictionloss", ALL),),
    "mass": (("body_mass", ALL), ("body_inertia", ALL)),
    # force = gain * ctrl + bias0 + bias1 * length + bias2 * velocity: all of it scales.
    "gain": (("actuator_gainprm", FIRST), ("actuator_biasprm", (slice(None), slice(0, 3)))),
    "damping": (("dof_damping", ALL),),
    "gravity": (("opt.gravity", ALL),),
}
# Brax's System is an MJX model whose own pipelines read fields of their own (`link.inertia`,
# `actuator.gain`, `dof.damping`, `gravity`): both are scaled, so that whichever its pipeline
# steps with changes; its contacts are MJX's collisions (`geom_friction`). No joint friction.
BRAX_MODEL_AXES: dict[str, tuple[tuple[str, tuple], ...]] = {
    "friction": MODEL_AXES["friction"],
    "mass": (*MODEL_AXES["mass"], ("link.inertia.mass", ALL), ("link.inertia.i", ALL)),
    "gain": (*MODEL_AXES["gain"], ("actuator.gain", ALL), ("actuator.bias_q", ALL), ("actuator.bias_qd", ALL)),
    "damping": (*MODEL_AXES["damping"], ("dof.damping", ALL)),
    "gravity": (*MODEL_AXES["gravity"], ("gravity", ALL)),
}
SIGNAL_AXES = ("obs-noise", "action-noise", "delay")
# Kicks to the simulator's state: a speed (m/s) added to its first joint at random moments.
PUSH = "push"
AXES = (*MODEL_AXES, PUSH, *SIGNAL_AXES)
# The axes that need a simulator inside the program (`SimulatesModel`).
SIMULATOR_AXES = (*MODEL_AXES, PUSH)
# The value at which an axis changes nothing.
NOMINAL = {**{name: 1.0 for name in MODEL_AXES}, PUSH: 0.0, **{name: 0.0 for name in SIGNAL_AXES}}
# A push comes at each control step with probability control_dt / PUSH_EVERY_S: once every
# PUSH_EVERY_S seconds on average, as Playground's locomotion tasks push (every 5 to 10 s).
PUSH_EVERY_S = 5.0


def _field(model: Any, field: str) -> Any:
    for name in field.split("."):
        model = getattr(model, name)
    return model


def _replaced(model: Any, field: str, value: Any) -> Any:
    """`model` with its (dotted) `field` replaced by `value`, each dataclass on the way copied."""
    name, _, rest = field.partition(".")
    return model.replace(**{name: _replaced(getattr(model, name), rest, value) if rest else value})


def model_axes(model: Any) -> dict[str, tuple[tuple[str, tuple], ...]]:
    """The model axes of `model` and the fields each scales: Brax's System's own, or MJX's."""
    return BRAX_MODEL_AXES if hasattr(model, "link") else MODEL_AXES


def scaled_model(model: Any, axis: str, factor: Any) -> Any:
    """The MJX model (or Brax System) `model` with the fields of `axis` scaled by `factor`
    (possibly traced)."""
    for field, index in model_axes(model)[axis]:
        model = _replaced(model, field, _field(model, field).at[index].multiply(factor))
    return model


def scale_in_place(mj_model: Any, axis: str, factor: float) -> None:
    """Scales the fields of `axis` in `mj_model`, a MuJoCo model on the host (its arrays are views)."""
    for field, index in MODEL_AXES[axis]:
        _field(mj_model, field)[index] *= factor


def simulator(env: Env) -> SimulatesModel | None:
    """The environment under `env`'s wrappers that steps an MJX model inside the program, if any."""
    while env is not None:
        if isinstance(env, SimulatesModel):
            return env
        env = getattr(env, "env", None)
    return None


def simulated_model(env: Env) -> Any | None:
    """The nominal MJX model that `env` (or the environment it wraps) steps, if it is one."""
    found = simulator(env)
    return None if found is None else found.model


def check_axes(env: Env, axes: tuple[str, ...]) -> None:
    """Refuses (UsageError, one line) an unknown axis, or one that `env` cannot apply or that
    would change nothing in its model."""
    check_known(axes)
    needs_simulator = [axis for axis in axes if axis in SIMULATOR_AXES]
    model = simulated_model(env)
    if needs_simulator and model is None:
        raise UsageError(
            f"{env.spec.name} has no MJX model that rpo_jax changes (cartpole's, ballbalance's, brax/'s, mjx-dmc/'s "
            f"and mjx-robot/'s), so {needs_simulator[0]} cannot change; its axes are {', '.join(SIGNAL_AXES)}"
        )
    check_model(env.spec.name, model, [axis for axis in axes if axis in MODEL_AXES])


def can_touch(model: Any) -> bool:
    """Whether any two geoms of `model` may be in contact: contacts on (mjDSBL_CONTACT unset) and
    an explicit pair, or a geom whose contype meets another's conaffinity."""
    contype, conaffinity = jnp.asarray(model.geom_contype), jnp.asarray(model.geom_conaffinity)
    meet = bool(jnp.any((contype[:, None] & conaffinity[None, :]) != 0))
    return not int(model.opt.disableflags) & 1 << 4 and (meet or int(model.npair) > 0)


def check_known(axes: tuple[str, ...]) -> None:
    """Refuses (one line) an axis that is none of `AXES`."""
    for axis in axes:
        if axis not in AXES:
            raise UsageError(f"unknown perturbation {axis!r}; the axes are {', '.join(AXES)}")


def check_model(name: str, model: Any, axes: list[str] | tuple[str, ...]) -> None:
    """Refuses (one line) a model axis of `axes` that would change nothing in `model`, MJX's or
    MuJoCo's: all its first field's values zero, or friction where no contact can happen."""
    for axis in axes:
        if axis not in model_axes(model):
            raise UsageError(f"{axis} changes nothing in {name}: Brax's pipelines have no {axis}")
        field = MODEL_AXES[axis][0][0]
        if (axis == "friction" and not can_touch(model)) or not bool(jnp.any(jnp.asarray(_field(model, field)) != 0)):
            raise UsageError(f"{axis} changes nothing in {name}: its model has no {field.split('.')[-1]} in use")


@struct.dataclass
class PerturbedState:
    inner: Any
    key: jax.Array
    actions: jax.Array  # [MAX_DELAY + 1, (N,) action_size] the latest actions, newest first
    values: jax.Array  # [axes] this episode's value of each axis


class Perturbed:
    """`env` with each axis of `ranges` (axis -> (low, high), possibly traced) at a value drawn per
    episode, uniformly, from its reset key (a delay: a whole number of steps in [low, high]);
    low == high fixes it. The model's fields scaled, noise on what it observes and on what it is
    told to do, its actions delayed. The simulator resets with the key it is given, so at nominal
    values the episodes are the unperturbed ones. A push (`PUSH`) adds its speed to the simulator's
    first joint: a free joint's horizontal velocity in a random direction, another joint's velocity
    with a random sign. `name`: the spec's name, where it differs. Over a batched environment (a
    host pool, which resets its episodes itself) the values are drawn once, for all its
    environments: give it fixed values."""

    def __init__(self, env: Env, ranges: dict[str, tuple[Any, Any]], name: str | None = None) -> None:
        self.env, self.axes = env, tuple(ranges)
        bounds = [jnp.asarray(ranges[axis], jnp.float32) for axis in self.axes]  # each [low, high]
        self.low, self.high = jnp.stack(bounds, axis=1) if bounds else jnp.zeros((2, 0))
        self.spec = env.spec if name is None else dataclasses.replace(env.spec, name=name)
        if hasattr(env, "num_envs"):  # a batched environment (a host pool): its values are fixed, the same for all
            self.num_envs = env.num_envs

    def _draw(self, key: jax.Array) -> jax.Array:
        u = jax.random.uniform(key, self.low.shape)
        values = self.low + (self.high - self.low) * u
        is_delay = jnp.asarray([axis == "delay" for axis in self.axes], bool)
        steps = jnp.minimum(jnp.floor(self.low + (self.high - self.low + 1) * u), self.high)
        return jnp.where(is_delay, steps, values)

    def _value(self, values: jax.Array, axis: str) -> jax.Array | float:
        return values[self.axes.index(axis)] if axis in self.axes else NOMINAL[axis]

    def _simulator(self, values: jax.Array) -> Env:
        """The environment with this episode's model."""
        changed = [axis for axis in MODEL_AXES if axis in self.axes]
        if not changed:
            return self.env

        def change(model: Any) -> Any:
            for axis in changed:
                model = scaled_model(model, axis, self._value(values, axis))
            return model

        return with_model(self.env, change)

    def reset(self, key: jax.Array) -> tuple[PerturbedState, TimeStep]:
        draw_key, noise_key, key = jax.random.split(jax.random.fold_in(key, 0x0B5E), 3)
        values = self._draw(draw_key)
        inner, ts = self._simulator(values).reset(key)
        actions = jnp.zeros((MAX_DELAY + 1, *ts.reward.shape, self.spec.action_size))
        return PerturbedState(inner, key, actions, values), self._observed(ts, noise_key, values)

    def step(self, state: PerturbedState, action: jax.Array) -> tuple[PerturbedState, TimeStep]:
        action_key, noise_key, key = jax.random.split(state.key, 3)
        noisy = action + self._value(state.values, "action-noise") * jax.random.normal(action_key, action.shape)
        low, high = jnp.asarray(self.spec.action_low), jnp.asarray(self.spec.action_high)
        actions = jnp.concatenate([jnp.clip(noisy, low, high)[None], state.actions[:-1]])
        delay = jnp.asarray(self._value(state.values, "delay")).astype(jnp.int32)
        inner = state.inner
        if PUSH in self.axes:  # its own key stream, so that the other axes' draws stay as they were
            inner = self._pushed(inner, jax.random.fold_in(action_key, 1), self._value(state.values, PUSH))
        inner, ts = self._simulator(state.values).step(inner, actions[delay])
        return state.replace(inner=inner, key=key, actions=actions), self._observed(ts, noise_key, state.values)

    def _pushed(self, state: Any, key: jax.Array, speed: jax.Array) -> Any:
        """`state` with a push of `speed` (m/s; rad/s on a hinge) on the first joint at this step,
        with probability control_dt / PUSH_EVERY_S."""
        sim = simulator(self.env)
        when, heading = jax.random.split(key)
        angle = jax.random.uniform(heading, (), maxval=2 * jnp.pi)
        velocity = jnp.zeros(sim.mj_model.nv)
        if int(sim.mj_model.jnt_type[0]) == 0:  # mjJNT_FREE: its first three dofs are its linear velocity
            velocity = velocity.at[:2].set(jnp.stack([jnp.cos(angle), jnp.sin(angle)]))
        else:
            velocity = velocity.at[0].set(jnp.where(angle < jnp.pi, 1.0, -1.0))
        kicked = jax.random.uniform(when) < sim.control_dt / PUSH_EVERY_S
        return pushed(self.env, state, jnp.where(kicked, speed, 0.0) * velocity)

    def _observed(self, ts: TimeStep, key: jax.Array, values: jax.Array) -> TimeStep:
        noise = self._value(values, "obs-noise") * jax.random.normal(key, ts.obs.shape)
        return ts.replace(obs=ts.obs + noise, final_obs=ts.final_obs + noise)


def parse_ranges(name: str, text: str) -> dict[str, tuple[float, float]]:
    """The ranges after a name's first SEPARATOR: 'mass=0.8:1.2+delay=0:2' -> {'mass': (0.8, 1.2),
    'delay': (0.0, 2.0)} (a single value fixes the axis); one line (UsageError) for anything else."""
    ranges: dict[str, tuple[float, float]] = {}
    for part in text.split(SEPARATOR):
        axis, equals, values = part.partition("=")
        if not equals or axis not in AXES:
            raise UsageError(f"env {name!r}: {part!r} is not AXIS=LOW:HIGH with AXIS one of {', '.join(AXES)}")
        if axis in ranges:
            raise UsageError(f"env {name!r}: {axis} is given twice")
        try:
            low, _, high = values.partition(":")
            bounds = (float(low), float(high or low))
        except ValueError:
            raise UsageError(f"env {name!r}: {part!r}: LOW and HIGH must be numbers") from None
        if not all(math.isfinite(b) for b in bounds) or not 0 <= bounds[0] <= bounds[1]:
            raise UsageError(f"env {name!r}: {part!r}: the range must be finite with 0 <= LOW <= HIGH")
        if axis == "delay" and (bounds[1] > MAX_DELAY or any(b != int(b) for b in bounds)):
            raise UsageError(f"env {name!r}: {part!r}: a delay is whole control steps in [0, {MAX_DELAY}]")
        ranges[axis] = bounds
    return ranges


def perturbed(env: Env, ranges: dict[str, tuple[float, float]], name: str) -> Perturbed:
    """`env` under `ranges` drawn per episode, named `name`; UsageError where it cannot apply them
    (a host-side simulator, or an axis its model lacks)."""
    if not hasattr(env, "reset") or getattr(env, "spec", None) is None or env.spec.backend == "host":
        raise UsageError(f"env {name!r}: perturbations apply to tasks simulated inside the program, not host-side ones")
    check_axes(env, tuple(ranges))
    return Perturbed(env, ranges, name)


def with_model(env: Env, change: Callable[[Any], Any]) -> Env:
    """A shallow copy of `env` (and of the wrappers down to its simulator) whose simulator steps
    `change(model)` (`SimulatesModel.with_model`); the original is untouched."""
    if isinstance(env, SimulatesModel):
        return env.with_model(change)
    if getattr(env, "env", None) is None:
        raise UsageError(f"{env.spec.name} has no MJX model to perturb")
    env = copy.copy(env)
    env.env = with_model(env.env, change)
    return env


def pushed(env: Env, state: Any, velocity: jax.Array) -> Any:
    """`state` of `env` with `velocity` [nv] added to its simulator's joint velocities
    (`SimulatesModel.pushed`), through the wrappers' states (each keeps its inner one in `inner`)."""
    if isinstance(env, SimulatesModel):
        return env.pushed(state, velocity)
    if getattr(env, "env", None) is None or not hasattr(state, "inner"):
        raise UsageError(f"{env.spec.name}: its state has no simulator to push")
    return state.replace(inner=pushed(env.env, state.inner, velocity))
