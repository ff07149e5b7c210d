"""IsaacGym's BallBalance rebuilt as an MJX model: a tray on three legs keeps a ball on it
(`ballbalance`). MuJoCo is imported when the model is built, not with this module, so that the
registry can list the environment without it."""

from __future__ import annotations

import functools
import math
import warnings
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from rpo_jax.envs.protocol import EnvSpec, StepsOwnModel, TimeStep, first_step

if TYPE_CHECKING:
    from mujoco import mjx

TRAY_RADIUS = 0.5
TRAY_HALF_THICKNESS = 0.01
# IsaacGym loads the cylinder as a convex prism of this many sides (slices_per_cylinder).
TRAY_SIDES = 40
LEG_RADIUS = 0.02
LEG_LENGTH = 0.36
# The legs hang from the tray and stand on the ground at this distance from the axis.
MOUNT_RADIUS = 0.4
LEG_ANGLES = (0.0, 2.0 * math.pi / 3.0, 4.0 * math.pi / 3.0)
# Each segment leans 45 degrees: the knee sits inside, straight between the mount and the foot.
LEG_REACH = LEG_LENGTH / math.sqrt(2.0)
# The upper hinge sits one leg radius below the tray's underside; the foot one leg radius
# above the ground. That puts the tray's centre at about 0.559 m.
MOUNT_DEPTH = TRAY_HALF_THICKNESS + LEG_RADIUS
TRAY_HEIGHT = 2.0 * LEG_REACH + MOUNT_DEPTH + LEG_RADIUS
BALL_RADIUS = 0.1

UPPER_HINGE_RANGE = (math.radians(-45.0), math.radians(45.0))
LOWER_HINGE_RANGE = (math.radians(-70.0), math.radians(90.0))
DRIVE_STIFFNESS = 4000.0
DRIVE_DAMPING = 100.0
CONTROL_DT = 0.01
ACTION_SPEED = 20.0

BALL_GOAL = (0.0, 0.0, 0.7)
FALL_HEIGHT = 1.5 * BALL_RADIUS
SENSOR_SCALE = 1.0 / 20.0
OBS_CLIP = 5.0

SPEC = EnvSpec("ballbalance", 24, 3, (-1.0,) * 3, (1.0,) * 3, 500, "mjx")


# The MJCF model; `ballbalance_xml` fills in the sizes and the three legs.
MODEL_TEMPLATE = """
<mujoco model="isaacgym_ballbalance">
  <compiler angle="radian"/>
  <!-- One Euler step per control step. Joint damping is explicit here (eulerdamp off): the
       drive's implicit part is in the armature, where the constraint solver sees it too.
       Newton converges in a few iterations on this small system (18 dofs, at most 9 + 6 + 4
       constraint rows), so a low cap keeps vmapped while-loops short. -->
  <option timestep="{control_dt}" gravity="0 0 -9.81" integrator="Euler" solver="Newton"
          iterations="4" ls_iterations="8">
    <flag eulerdamp="disable"/>
  </option>
  <asset>
    <mesh name="tray" vertex="{tray_vertices}"/>
  </asset>
  <default>
    <!-- Nothing collides by default: the only contact is the explicit ball-tray pair. -->
    <geom contype="0" conaffinity="0"/>
    <!-- Near-hard pins and joint limits (impedance 0.99 to 0.999 instead of 0.9 to 0.95), so
         that when the three drives pull against each other the drives give way, as they do
         against IsaacGym's 5e7 N/m attractors, rather than the feet or the hinge stops. -->
    <equality solimp="0.99 0.999 0.001"/>
    <joint type="hinge" limited="true" solimplimit="0.99 0.999 0.001"/>
    <default class="leg">
      <geom type="capsule" size="{leg_radius}" density="1000"/>
    </default>
  </default>
  <worldbody>
    {anchors}
    <body name="tray" pos="0 0 {tray_height}">
      <freejoint name="tray"/>
      <geom name="tray" type="mesh" mesh="tray" density="100"/>
      {legs}
    </body>
    <body name="ball" pos="0 0 1.5">
      <freejoint name="ball"/>
      <geom name="ball" type="sphere" size="{ball_radius}" density="200"/>
    </body>
  </worldbody>
  <contact>
    <pair geom1="ball" geom2="tray"/>
  </contact>
  <equality>
    {pins}
  </equality>
  <actuator>
    {drives}
  </actuator>
  <sensor>
    {sensors}
  </sensor>
</mujoco>
"""


def _leg(i: int, angle: float, drive_armature: float, drive_damping: float) -> tuple[str, str, str, str]:
    """Leg i's bodies, its foot's anchor on the ground, the pin between them and its knee drive."""
    upper_range = "{} {}".format(*UPPER_HINGE_RANGE)
    lower_range = "{} {}".format(*LOWER_HINGE_RANGE)
    x, y = MOUNT_RADIUS * math.cos(angle), MOUNT_RADIUS * math.sin(angle)
    # Each leg's frame is the tray's turned by the leg's angle: x points outwards, y along
    # the tray's rim, which is the axis of both hinges.
    leg = f"""
      <body name="upper_leg{i}" pos="{x} {y} {-MOUNT_DEPTH}" euler="0 0 {angle}">
        <joint name="upper_hinge{i}" axis="0 1 0" range="{upper_range}"/>
        <geom class="leg" fromto="0 0 0 {-LEG_REACH} 0 {-LEG_REACH}"/>
        <site name="mount{i}"/>
        <body name="lower_leg{i}" pos="{-LEG_REACH} 0 {-LEG_REACH}">
          <joint name="lower_hinge{i}" axis="0 1 0" range="{lower_range}"
                 armature="{drive_armature}" damping="{drive_damping}"/>
          <geom class="leg" fromto="0 0 0 {LEG_REACH} 0 {-LEG_REACH}"/>
          <site name="foot{i}" pos="{LEG_REACH} 0 {-LEG_REACH}"/>
        </body>
      </body>"""
    anchor = f'<site name="anchor{i}" pos="{x} {y} {LEG_RADIUS}"/>'
    pin = f'<connect site1="foot{i}" site2="anchor{i}"/>'
    drive = f'<position name="drive{i}" joint="lower_hinge{i}" kp="{DRIVE_STIFFNESS}" ctrlrange="{lower_range}"/>'
    return leg, anchor, pin, drive


# What only videos see (`render_model`): the scene (`video_scene`) with the floor under the robot's
# feet, colours, and a camera in front of the tray and above it, so that the ball shows against it.
RENDER_CAMERA = '<camera name="front" pos="0 -3.2 1.3" xyaxes="1 0 0 0 0.15 1"/>'
RENDER_COLOURS = {'name="tray"': "0.25 0.45 0.7 1", 'name="ball"': "0.95 0.55 0.15 1", 'type="capsule"': "0.7 0.7 0.72 1"}


def render_xml() -> str:
    """The model dressed for videos (`video_scene`, `RENDER_CAMERA`, `RENDER_COLOURS`): the same
    bodies and joints."""
    from rpo_jax.envs.mjx_support import video_scene

    xml = ballbalance_xml().replace("  <worldbody>", video_scene(0.0) + "\n    " + RENDER_CAMERA, 1)
    for marker, rgba in RENDER_COLOURS.items():
        xml = xml.replace(f"<geom {marker}", f'<geom {marker} rgba="{rgba}"', 1)
    return xml


def ballbalance_xml() -> str:
    """The MJCF model. Angles in radians; all lengths and masses from the constants above."""
    h = CONTROL_DT
    # The PD drive integrated implicitly, as PhysX does, written in terms MuJoCo's explicit
    # Euler step understands: backward Euler on kp (target - q) - kd qdot adds
    # h kd + h^2 kp to the joint's inertia and h kp to its damping (see the class docstring).
    drive_armature = h * DRIVE_DAMPING + h * h * DRIVE_STIFFNESS
    drive_damping = DRIVE_DAMPING + h * DRIVE_STIFFNESS
    legs, anchors, pins, drives = zip(*(_leg(i, angle, drive_armature, drive_damping) for i, angle in enumerate(LEG_ANGLES)))
    rim = [2.0 * math.pi * k / TRAY_SIDES for k in range(TRAY_SIDES)]
    tray_vertices = " ".join(
        f"{TRAY_RADIUS * math.cos(a)} {TRAY_RADIUS * math.sin(a)} {z}"
        for a in rim
        for z in (-TRAY_HALF_THICKNESS, TRAY_HALF_THICKNESS)
    )
    forces = "".join(f'<force site="mount{i}"/>' for i in range(3))
    torques = "".join(f'<torque site="mount{i}"/>' for i in range(3))
    return MODEL_TEMPLATE.format(
        control_dt=CONTROL_DT, tray_vertices=tray_vertices, leg_radius=LEG_RADIUS, anchors="".join(anchors),
        tray_height=TRAY_HEIGHT, legs="".join(legs), ball_radius=BALL_RADIUS, pins="".join(pins),
        drives="".join(drives), sensors=forces + torques,
    )  # fmt: skip


@struct.dataclass
class BallBalanceState:
    qpos: jax.Array  # [20] tray (7), upper and lower hinge of each leg (6), ball (7)
    qvel: jax.Array  # [18] tray (6), hinges (6), ball (6)
    qacc_warmstart: jax.Array  # [18] the last step's accelerations, the solver's first guess
    target: jax.Array  # [3] position targets of the lower hinges


class BallBalance(StepsOwnModel):
    """IsaacGym's BallBalance rebuilt as an MJX model.

    A tray (radius 0.5 m, 2 cm thick, density 100) on a free joint rests at about 0.559 m on
    three legs at 0, 120 and 240 degrees. Each leg is two capsules (radius 0.02 m, length
    0.36 m, density 1000): the upper one hangs from a passive hinge (+-45 deg) under the tray at
    radius 0.4 m, the lower one turns on an actuated knee (-70 to +90 deg), and its foot is
    pinned to the ground at (0.4 cos t, 0.4 sin t, 0.02) by an equality `connect` constraint.
    A ball (radius 0.1 m, density 200) falls onto the tray.

    Action (3) in [-1, 1]: every step each knee's position target moves by 0.01 * 20 * action
    and is clamped to the knee's range; targets are 0 after a reset. The knees are
    PD-controlled, kp 4000 and kd 100, 1 physics step of 0.01 s per control step.

    Observation (24), clipped to +-5: knee angles (3), knee velocities (3), ball position (3),
    ball linear velocity (3), then the three force/torque sensors divided by 20: the x-force
    of sensors 0, 1, 2, then the x-torques of the three, their y-torques, their z-torques.
    Reward 1 / (1 + |ball position - (0, 0, 0.7)|) / (1 + |ball velocity|). The episode
    terminates when the ball's centre is below 0.15 m; `TimeLimit` truncates it after 500
    steps. A reset puts the robot back at rest and drops the ball from height U(1, 2), at a
    distance d ~ U(0.001, 0.5) from the axis in a uniform direction, moving towards the axis
    at ((d - 0.001) / 0.499) * U(0, 5) m/s and downwards at 5 m/s.

    Choices where MuJoCo differs from PhysX:
    - Drive: a `position` actuator (kp 4000) on each knee. PhysX integrates its joint drives
      implicitly; an explicit kp = 4000 and kd = 100 on legs this light diverge at 0.01 s
      (with MuJoCo's own implicit damping too, since the constraint solver does not see it).
      Backward Euler on the drive force f = kp (target - q) - kd qdot gives
      (M + h kd + h^2 kp) qacc = ... + kp (target - q) - (kd + h kp) qdot, so the knee gets
      armature h kd + h^2 kp = 1.4 and damping kd + h kp = 140, applied explicitly. This is the
      implicit PD drive exactly, and stable at any stiffness; the armature is the drive's
      implicit response, not extra inertia of the leg.
    - Tray: IsaacGym meshes the cylinder as a 40-sided convex prism (slices_per_cylinder), and
      so does this model, mass included (1.564 kg rather than 1.571). It also avoids MJX's
      sphere-cylinder collider, a few steps of descent on signed distances whose normal tilts
      with the ball's offset: a ball resting near the centre rolled off within 5 s.
    - Feet: equality `connect` constraints instead of IsaacGym's stiff attractors (5e7 N/m),
      and the hinge stops as joint limits, both with impedance raised to 0.99-0.999. A foot
      gives under 0.1 mm under the robot's load. MuJoCo relaxes a constraint over at least two
      steps (0.02 s), so under fast knee motions that fight each other the feet still slip by
      up to a few cm and the upper hinges pass their stops by up to about 0.3 rad.
    - Sensors: IsaacGym's rigid-body force sensors report the net force on the tray (the same
      force at all three, about the tray's mass times its acceleration) with the torque taken
      at each sensor. MuJoCo's `force` and `torque` sensors measure the load a joint carries;
      here one sits at each upper hinge, so each reports the load its leg takes from the tray.
      The readings are turned into the force and torque the leg exerts on the tray, in the
      tray's axes, with the torque taken about the spec's sensor point (0.4 cos t,
      0.4 sin t, 0) in the tray's frame, 3 cm above the hinge. At rest the three z-forces add
      up to the weight of tray and ball.
    - Contacts: only the ball-tray pair collides (default friction 1, no restitution).
      There is no ground: the feet are pinned and the episode ends before the ball (radius 0.1)
      could reach the ground, so no other contact can matter before termination. Legs that
      the ball might brush on its way down past the rim do not touch it.
    - Solver: Newton, at most 4 iterations and 8 line-search steps, warm-started from the
      previous step's accelerations (kept in the state).
    - Sensor readings come from the forces of the step just taken, as in IsaacGym; the first
      observation of an episode carries the readings of the robot at rest with the ball in
      the air, computed once when the environment is built.
    """

    ball_distance_range = (0.001, 0.5)
    ball_height_range = (1.0, 2.0)
    ball_max_horizontal_speed = 5.0
    ball_vertical_speed = -5.0
    spec = SPEC

    def __init__(self) -> None:
        from rpo_jax.envs.mjx_support import mujoco, put_model

        self.mj_model = mujoco.MjModel.from_xml_string(ballbalance_xml())
        self.control_dt = CONTROL_DT
        with warnings.catch_warnings():
            # MJX warns about the 40-gon faces for its polygon colliders; the sphere-convex one
            # used here walks a face's edges exactly, whatever their number.
            warnings.filterwarnings("ignore", "Mesh .* coplanar face", UserWarning)
            self.model, self.data_template = put_model(self.mj_model)
        m = self.mj_model
        lower = [m.joint(f"lower_hinge{i}") for i in range(3)]
        self.knee_qpos = np.array([j.qposadr[0] for j in lower])
        self.knee_dof = np.array([j.dofadr[0] for j in lower])
        ball = m.joint("ball")
        self.ball_qpos, self.ball_dof = int(ball.qposadr[0]), int(ball.dofadr[0])
        self.tray_body = m.body("tray").id
        self.mount_sites = np.array([m.site(f"mount{i}").id for i in range(3)])
        self.knee_low = jnp.asarray(LOWER_HINGE_RANGE[0], jnp.float32)
        self.knee_high = jnp.asarray(LOWER_HINGE_RANGE[1], jnp.float32)

        # The robot at rest with the ball far above it: the state every episode starts from.
        rest = mujoco.MjData(m)
        rest.qpos[self.ball_qpos + 2] = 10.0
        mujoco.mj_forward(m, rest)
        self.rest_qpos = jnp.asarray(m.qpos0, jnp.float32)
        self.rest_qacc = jnp.asarray(rest.qacc, jnp.float32)
        self.rest_sensors = self._sensor_obs(
            jnp.asarray(rest.sensordata, jnp.float32),
            jnp.asarray(rest.site_xmat[self.mount_sites].reshape(3, 3, 3), jnp.float32),
            jnp.asarray(rest.xmat[self.tray_body].reshape(3, 3), jnp.float32),
        )

    @staticmethod
    def qpos(state: BallBalanceState) -> jax.Array:
        return state.qpos

    @functools.cached_property
    def render_model(self) -> Any:
        """A copy of the model for videos only (`render_xml`); training never sees it."""
        from rpo_jax.envs.mjx_support import mujoco

        return mujoco.MjModel.from_xml_string(render_xml())

    def reset(self, key: jax.Array) -> tuple[BallBalanceState, TimeStep]:
        k_dist, k_dir, k_height, k_speed = jax.random.split(key, 4)
        low, high = self.ball_distance_range
        distance = jax.random.uniform(k_dist, (), minval=low, maxval=high)
        heading = jax.random.uniform(k_dir, (), maxval=2.0 * jnp.pi)
        direction = jnp.stack([jnp.cos(heading), jnp.sin(heading)])
        height = jax.random.uniform(k_height, (), minval=self.ball_height_range[0], maxval=self.ball_height_range[1])
        speed = (distance - low) / (high - low) * jax.random.uniform(k_speed, (), maxval=self.ball_max_horizontal_speed)
        b, v = self.ball_qpos, self.ball_dof
        qpos = self.rest_qpos.at[b : b + 2].set(distance * direction).at[b + 2].set(height)
        qpos = qpos.at[b + 3 : b + 7].set(jnp.array([1.0, 0.0, 0.0, 0.0]))
        qvel = jnp.zeros(self.mj_model.nv).at[v : v + 2].set(-speed * direction).at[v + 2].set(self.ball_vertical_speed)
        state = BallBalanceState(qpos=qpos, qvel=qvel, qacc_warmstart=self.rest_qacc, target=jnp.zeros(3))
        return state, first_step(self._observe(qpos, qvel, self.rest_sensors))

    def step(self, state: BallBalanceState, action: jax.Array) -> tuple[BallBalanceState, TimeStep]:
        state, data = self.simulate(state, action)
        return state, self.time_step(data)

    def simulate(self, state: BallBalanceState, action: jax.Array) -> tuple[BallBalanceState, mjx.Data]:
        """Moves the knee targets by the action and advances the physics one control step. The
        returned data holds the new qpos and qvel, and the sensor readings and frames of the
        forces that acted during the step."""
        from rpo_jax.envs.mjx_support import physics_step

        action = jnp.clip(action, -1.0, 1.0)
        target = jnp.clip(state.target + CONTROL_DT * ACTION_SPEED * action, self.knee_low, self.knee_high)
        data = self.data_template.replace(qpos=state.qpos, qvel=state.qvel, qacc_warmstart=state.qacc_warmstart, ctrl=target)
        data = physics_step(self.model, data)
        return BallBalanceState(qpos=data.qpos, qvel=data.qvel, qacc_warmstart=data.qacc, target=target), data

    def time_step(self, data: mjx.Data) -> TimeStep:
        """Observation, reward and termination of the state a step reached."""
        sensors = self._sensor_obs(data.sensordata, data.site_xmat[self.mount_sites], data.xmat[self.tray_body])
        obs = self._observe(data.qpos, data.qvel, sensors)
        ball_pos = data.qpos[self.ball_qpos : self.ball_qpos + 3]
        ball_vel = data.qvel[self.ball_dof : self.ball_dof + 3]
        terminated = ball_pos[2] < FALL_HEIGHT
        return TimeStep(obs, ball_reward(ball_pos, ball_vel), terminated, jnp.zeros((), bool), obs)

    def _observe(self, qpos: jax.Array, qvel: jax.Array, sensors: jax.Array) -> jax.Array:
        b, v = self.ball_qpos, self.ball_dof
        obs = jnp.concatenate([qpos[self.knee_qpos], qvel[self.knee_dof], qpos[b : b + 3], qvel[v : v + 3], sensors])
        return jnp.clip(obs, -OBS_CLIP, OBS_CLIP)

    @staticmethod
    def _sensor_obs(sensordata: jax.Array, mount_xmat: jax.Array, tray_xmat: jax.Array) -> jax.Array:
        """The 12 sensor observations from raw sensordata [18] (3 forces, then 3 torques, each in
        its site's frame), the sites' rotations [3, 3, 3] and the tray's rotation [3, 3]."""
        force, torque = tray_loads(sensordata, mount_xmat, tray_xmat)
        return SENSOR_SCALE * jnp.concatenate([force[:, 0], torque.T.reshape(-1)])


def tray_loads(sensordata: jax.Array, mount_xmat: jax.Array, tray_xmat: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Force and torque [3, 3] (one row per leg) that each leg exerts on the tray, in the tray's
    axes, the torque about the leg's sensor point 3 cm above its hinge.

    MuJoCo's readings are the load the tray puts on the leg, in the frame of the site at the
    hinge, so they change sign and frame here."""
    readings = sensordata.reshape(2, 3, 3)
    site_to_tray = jnp.einsum("ji,sjk->sik", tray_xmat, mount_xmat)
    force = -jnp.einsum("sik,sk->si", site_to_tray, readings[0])
    torque_at_hinge = -jnp.einsum("sik,sk->si", site_to_tray, readings[1])
    hinge_from_sensor = jnp.array([0.0, 0.0, -MOUNT_DEPTH])
    return force, torque_at_hinge + jnp.cross(hinge_from_sensor, force)


def ball_reward(ball_pos: jax.Array, ball_vel: jax.Array) -> jax.Array:
    """IsaacGym's reward: closeness to the point 0.7 m above the tray's centre times slowness."""
    distance = jnp.linalg.norm(ball_pos - jnp.asarray(BALL_GOAL))
    return 1.0 / (1.0 + distance) / (1.0 + jnp.linalg.norm(ball_vel))
