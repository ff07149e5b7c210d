"""IsaacGym's Cartpole on MJX (`cartpole`). MuJoCo is imported when the model is built, not
with this module, so that the registry can list the environment without it."""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from rpo_jax.envs.protocol import EnvSpec, StepsOwnModel, TimeStep, first_step

SPEC = EnvSpec("cartpole", 4, 1, (-1.0,), (1.0,), 500, "mjx")

CARTPOLE_XML = """
<mujoco model="isaacgym_cartpole">
  <!-- 60 Hz control with 2 substeps. Contacts are off (nothing touches), and so is the
       constraint solver: the rail limit of +-4 m can never bind because the episode ends at
       |x| > 3 m and covering 1 m in one 1/60 s step would take 60 m/s. -->
  <option timestep="0.008333333333333333" gravity="0 0 -9.81" integrator="Euler">
    <flag contact="disable" constraint="disable"/>
  </option>
  <worldbody>
    <geom name="rail" type="box" size="4 0.02 0.02" contype="0" conaffinity="0"/>
    <body name="cart">
      <joint name="slider" type="slide" axis="1 0 0" limited="true" range="-4 4"/>
      <geom name="cart" type="box" size="0.1 0.125 0.1" mass="1" contype="0" conaffinity="0"/>
      <body name="pole" pos="0 0.12 0">
        <joint name="hinge" type="hinge" axis="0 1 0"/>
        <geom name="pole" type="box" size="0.02 0.03 0.5" pos="0 0 0.47" mass="1"
              contype="0" conaffinity="0"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="push" joint="slider" gear="400" ctrllimited="true" ctrlrange="-1 1"/>
  </actuator>
</mujoco>
"""


# What only videos see (`render_model`): the scene (`video_scene`) with the floor below the
# swinging pole, colours, and a camera beside the cart that follows it along the rail (the floor's
# squares show the motion).
RENDER_FLOOR_HEIGHT = -1.1
RENDER_CAMERA = """<body name="cart">
      <camera name="side" mode="trackcom" pos="0 -4.5 0.6" xyaxes="1 0 0 0 0.25 1"/>"""
RENDER_COLOURS = {"rail": "0.15 0.15 0.2 1", "cart": "0.85 0.45 0.15 1", "pole": "0.95 0.8 0.3 1"}


def render_xml() -> str:
    """CARTPOLE_XML dressed for videos (`video_scene`, `RENDER_CAMERA`, `RENDER_COLOURS`): the same
    bodies and joints."""
    from rpo_jax.envs.mjx_support import video_scene

    xml = CARTPOLE_XML.replace("  <worldbody>", video_scene(RENDER_FLOOR_HEIGHT), 1)
    xml = xml.replace('<body name="cart">', RENDER_CAMERA, 1)
    for name, rgba in RENDER_COLOURS.items():
        xml = xml.replace(f'<geom name="{name}"', f'<geom name="{name}" rgba="{rgba}"', 1)
    return xml


@struct.dataclass
class CartpoleState:
    qpos: jax.Array  # [2] cart position, pole angle
    qvel: jax.Array  # [2] cart velocity, pole angular velocity


class Cartpole(StepsOwnModel):
    """IsaacGym's Cartpole rebuilt as an MJX model.

    Observation (4): cart position, cart velocity, pole angle, pole angular velocity, clipped
    to +-5. Action (1) in [-1, 1], times 400 N on the cart (the motor's gear). Reward per step
    1 - angle^2 - 0.01 |cart velocity| - 0.005 |pole angular velocity|; when |cart position| > 3
    or |pole angle| > pi/2 that step's reward is -2 and the episode terminates. Episodes are
    truncated after 500 steps by `TimeLimit`. Resets draw both joint positions from U(-0.1, 0.1)
    and both velocities from U(-0.25, 0.25).

    Differences from PhysX: the pole's inertia follows from its box geometry and mass; the
    rail limit is declared but, with MuJoCo's constraint solver off, not enforced (it can never
    bind before termination, see the model). Only qpos and qvel are carried between steps:
    with no contacts and no constraints the rest of mjx.Data is recomputed by every step.
    """

    substeps = 2
    reset_position_range = 0.1
    reset_velocity_range = 0.25
    spec = SPEC

    def __init__(self) -> None:
        from rpo_jax.envs.mjx_support import mujoco, put_model

        self.mj_model = mujoco.MjModel.from_xml_string(CARTPOLE_XML)
        self.model, self.data_template = put_model(self.mj_model)
        self.control_dt = self.substeps * float(self.mj_model.opt.timestep)

    @staticmethod
    def qpos(state: CartpoleState) -> jax.Array:
        return state.qpos

    @functools.cached_property
    def render_model(self) -> Any:
        """A copy of the model for videos only (`render_xml`); training never sees it."""
        from rpo_jax.envs.mjx_support import mujoco

        return mujoco.MjModel.from_xml_string(render_xml())

    def reset(self, key: jax.Array) -> tuple[CartpoleState, TimeStep]:
        kq, kv = jax.random.split(key)
        p, v = self.reset_position_range, self.reset_velocity_range
        state = CartpoleState(
            qpos=jax.random.uniform(kq, (2,), minval=-p, maxval=p),
            qvel=jax.random.uniform(kv, (2,), minval=-v, maxval=v),
        )
        return state, first_step(self._observe(state))

    def step(self, state: CartpoleState, action: jax.Array) -> tuple[CartpoleState, TimeStep]:
        from rpo_jax.envs.mjx_support import physics_step

        data = self.data_template.replace(qpos=state.qpos, qvel=state.qvel, ctrl=jnp.clip(action, -1.0, 1.0))
        for _ in range(self.substeps):
            data = physics_step(self.model, data)
        state = CartpoleState(qpos=data.qpos, qvel=data.qvel)
        x, angle = state.qpos
        x_dot, angle_dot = state.qvel
        terminated = (jnp.abs(x) > 3.0) | (jnp.abs(angle) > jnp.pi / 2)
        reward = 1.0 - angle**2 - 0.01 * jnp.abs(x_dot) - 0.005 * jnp.abs(angle_dot)
        reward = jnp.where(terminated, -2.0, reward)
        obs = self._observe(state)
        return state, TimeStep(obs, reward, terminated, jnp.zeros((), bool), obs)

    @staticmethod
    def _observe(state: CartpoleState) -> jax.Array:
        x, angle = state.qpos
        x_dot, angle_dot = state.qvel
        return jnp.clip(jnp.stack([x, x_dot, angle, angle_dot]), -5.0, 5.0)
