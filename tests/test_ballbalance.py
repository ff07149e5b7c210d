"""BallBalance on MJX: the model, observation, reward, termination, resets, the time limit under
the vector wrappers, and a short training run.

An MJX step takes seconds to compile on a CPU, so the environment tests share one compiled
program: 500 steps of two environments under VectorEnv (its time limit and auto-reset), with the
simulator's sensor data of each step passed out through `TimeStep.info`."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from rpo_jax.run.records import metric_arrays
from rpo_jax.envs.recipes import PRESETS
from rpo_jax.envs import VectorEnv, make_env
from rpo_jax.envs import ballbalance as bb
from rpo_jax.ppo import make_train

GRAVITY = 9.81
REST_HEIGHT = bb.TRAY_HEIGHT + bb.TRAY_HALF_THICKNESS + bb.BALL_RADIUS  # ball centre on the tray
NUM_ENVS, NUM_STEPS = 2, 500
BALL_QPOS, BALL_DOF = 13, 12  # the ball's free joint follows the tray's and the six hinges
KNEE_QPOS, KNEE_DOF = [8, 10, 12], [7, 9, 11]


class WithSensorData:
    """BallBalance whose steps also report the raw sensor data and frames they computed."""

    def __init__(self, env: bb.BallBalance) -> None:
        self.env, self.spec = env, env.spec

    def reset(self, key):
        return self.env.reset(key)

    def step(self, state, action):
        state, data = self.env.simulate(state, action)
        info = {
            "sensordata": data.sensordata,
            "mount_xmat": data.site_xmat[self.env.mount_sites],
            "tray_xmat": data.xmat[self.env.tray_body],
        }
        return state, self.env.time_step(data).replace(info=info)


@pytest.fixture(scope="module")
def env():
    return make_env("ballbalance")


@pytest.fixture(scope="module")
def vector_env(env):
    return VectorEnv(WithSensorData(env), NUM_ENVS)


@pytest.fixture(scope="module")
def rollout(vector_env):
    """(state, actions [NUM_STEPS, NUM_ENVS, 3]) -> the TimeSteps and the environments' own
    states after each step, on the host."""

    def body(state, action):
        state, ts = vector_env.step(state, action)
        return state, (ts, state.envs.inner)

    run = jax.jit(lambda state, actions: jax.lax.scan(body, state, actions)[1])
    return lambda state, actions: jax.device_get(run(state, jnp.asarray(actions, jnp.float32)))


def start(vector_env, seed=0, ball_pos=None, ball_vel=None, target=None):
    """Fresh environments, optionally with the ball put at ball_pos [NUM_ENVS, 3] moving at
    ball_vel, and the knee targets set."""
    state, _ = vector_env.reset(jax.random.PRNGKey(seed))
    inner = state.envs.inner
    if ball_pos is not None:
        b, v = BALL_QPOS, BALL_DOF
        qpos = inner.qpos.at[:, b : b + 3].set(jnp.asarray(ball_pos, jnp.float32))
        ball_vel = np.zeros((NUM_ENVS, 3)) if ball_vel is None else ball_vel
        qvel = inner.qvel.at[:, v : v + 3].set(jnp.asarray(ball_vel, jnp.float32))
        inner = inner.replace(qpos=qpos, qvel=qvel)
    if target is not None:
        inner = inner.replace(target=jnp.asarray(target, jnp.float32))
    return state.replace(envs=state.envs.replace(inner=inner))


def pick(tree, t, e):
    return jax.tree.map(lambda x: x[t, e], tree)


def expected_obs(state, info):
    force, torque = bb.tray_loads(info["sensordata"], info["mount_xmat"], info["tray_xmat"])
    force, torque = np.asarray(force), np.asarray(torque)
    obs = np.concatenate([
        state.qpos[KNEE_QPOS], state.qvel[KNEE_DOF],
        state.qpos[BALL_QPOS : BALL_QPOS + 3], state.qvel[BALL_DOF : BALL_DOF + 3],
        force[:, 0] / 20, torque[:, 0] / 20, torque[:, 1] / 20, torque[:, 2] / 20,
    ])  # fmt: skip
    return np.clip(obs, -5.0, 5.0)


def expected_reward(state):
    pos = np.asarray(state.qpos[BALL_QPOS : BALL_QPOS + 3], np.float64)
    vel = np.asarray(state.qvel[BALL_DOF : BALL_DOF + 3], np.float64)
    return 1.0 / (1.0 + np.linalg.norm(pos - [0.0, 0.0, 0.7])) / (1.0 + np.linalg.norm(vel))


@pytest.fixture(scope="module")
def resting(vector_env, rollout):
    """Env 0: the ball put at rest on the tray's centre; env 1: the ball far above (in free fall
    for the whole run, so the tray carries only itself). Zero action throughout."""
    state = start(vector_env, ball_pos=[[0.0, 0.0, REST_HEIGHT], [0.0, 0.0, 2000.0]])
    return rollout(state, np.zeros((NUM_STEPS, NUM_ENVS, 3)))


# --------------------------------------------------------------------------------------------
# The model


def test_spec_and_model(env):
    spec = env.spec
    assert (spec.name, spec.observation_size, spec.action_size, spec.max_episode_steps) == ("ballbalance", 24, 3, 500)
    assert spec.action_low == (-1.0,) * 3 and spec.action_high == (1.0,) * 3
    m = env.mj_model
    assert (m.nq, m.nv, m.nu, m.neq) == (20, 18, 3, 3)
    assert bb.TRAY_HEIGHT == pytest.approx(0.559, abs=5e-4)
    masses = {name: m.body(name).mass[0] for name in ("tray", "upper_leg0", "lower_leg2", "ball")}
    # The tray is a 40-sided prism inscribed in the 0.5 m circle, as IsaacGym meshes it.
    assert masses["tray"] == pytest.approx(100 * 0.02 * 20 * 0.5**2 * np.sin(2 * np.pi / 40))
    assert masses["ball"] == pytest.approx(200 * 4 / 3 * np.pi * 0.1**3)  # about 0.84 kg
    assert masses["upper_leg0"] == pytest.approx(1000 * (np.pi * 0.02**2 * 0.36 + 4 / 3 * np.pi * 0.02**3))
    assert masses["lower_leg2"] == masses["upper_leg0"]
    # Only the ball and the tray can touch.
    assert np.all(m.geom_contype == 0) and np.all(m.geom_conaffinity == 0)
    assert m.npair == 1 and {m.pair_geom1[0], m.pair_geom2[0]} == {m.geom("ball").id, m.geom("tray").id}
    # At rest the feet stand on their ground anchors.
    data = mujoco.MjData(m)
    mujoco.mj_kinematics(m, data)
    for i, angle in enumerate(bb.LEG_ANGLES):
        anchor = [0.4 * np.cos(angle), 0.4 * np.sin(angle), 0.02]
        np.testing.assert_allclose(data.site_xpos[m.site(f"foot{i}").id], anchor, atol=1e-6)
        np.testing.assert_allclose(data.site_xpos[m.site(f"anchor{i}").id], anchor, atol=1e-6)
        np.testing.assert_allclose(np.degrees(m.joint(f"upper_hinge{i}").range), [-45, 45])
        np.testing.assert_allclose(np.degrees(m.joint(f"lower_hinge{i}").range), [-70, 90])


# --------------------------------------------------------------------------------------------
# Steps


def test_observation_layout_and_reward_formula(vector_env, rollout):
    state = start(vector_env, 3, ball_pos=[[0.1, -0.05, REST_HEIGHT + 0.05]] * 2, ball_vel=[[0.3, 0.2, -0.5]] * 2)
    actions = np.zeros((NUM_STEPS, NUM_ENVS, 3))
    actions[:3, 0] = [[0.5, -0.3, 0.1], [-0.2, 0.4, 0.0], [0.0, 0.0, 0.0]]
    actions[:3, 1] = [[-0.4, 0.2, 0.3], [0.1, 0.1, -0.2], [0.3, 0.0, 0.0]]
    ts, states = rollout(state, actions)
    for t in range(20):
        for e in range(NUM_ENVS):
            obs, state = ts.obs[t, e], pick(states, t, e)
            assert not ts.terminated[t, e] and not ts.truncated[t, e]
            assert np.all(np.abs(obs) < 5.0)  # nothing clipped: every value is compared as is
            np.testing.assert_allclose(obs, expected_obs(state, pick(ts.info, t, e)), rtol=1e-5, atol=1e-6)
            np.testing.assert_array_equal(ts.final_obs[t, e], obs)
            np.testing.assert_allclose(ts.reward[t, e], expected_reward(state), rtol=1e-5)
    assert np.all(ts.obs[2, :, :3] != 0.0) and np.all(ts.obs[2, :, 12:] != 0.0)  # knees moved, sensors read


def test_observation_is_clipped_to_plus_minus_5(vector_env, rollout):
    state = start(vector_env, ball_pos=[[0.0, 0.0, 3.0]] * 2, ball_vel=[[9.0, -7.0, 0.0], [-6.0, 5.5, 0.0]])
    ts, states = rollout(state, np.zeros((NUM_STEPS, NUM_ENVS, 3)))
    np.testing.assert_array_equal(ts.obs[0, :, 9:11], [[5.0, -5.0], [-5.0, 5.0]])
    for e in range(NUM_ENVS):
        expected = expected_obs(pick(states, 0, e), pick(ts.info, 0, e))
        np.testing.assert_allclose(ts.obs[0, e], expected, rtol=1e-5, atol=1e-6)


def test_knee_targets_move_by_dt_times_20_times_action_and_stay_in_range(vector_env, rollout):
    state = start(vector_env, target=[[0.0, 0.0, 0.0], [1.55, -1.2, 0.0]])
    actions = np.zeros((NUM_STEPS, NUM_ENVS, 3))
    actions[0] = [[1.0, -0.5, 3.0], [1.0, -1.0, -0.25]]  # 3.0 is clipped to 1
    _, states = rollout(state, actions)
    expected = [[0.2, -0.1, 0.2], [np.radians(90), np.radians(-70), -0.05]]
    np.testing.assert_allclose(states.target[0], expected, rtol=1e-6)
    np.testing.assert_array_equal(states.target[1], states.target[0])  # zero action holds them


@pytest.mark.parametrize(
    "cases",
    [
        [(0.155, -2.0, True), (0.16, 0.0, False)],
        [(0.14, 0.0, True), (REST_HEIGHT, 0.0, False)],
    ],
)
def test_episode_terminates_when_the_ball_falls_below_0_15(vector_env, rollout, cases):
    # Beside the tray, or on it.
    pos = [[0.8 if height < 0.5 else 0.0, 0.0, height] for height, _, _ in cases]
    state = start(vector_env, ball_pos=pos, ball_vel=[[0.0, 0.0, vz] for _, vz, _ in cases])
    ts, _ = rollout(state, np.zeros((NUM_STEPS, NUM_ENVS, 3)))
    for e, (_, _, ends) in enumerate(cases):
        assert bool(ts.final_obs[0, e, 8] < 0.15) == ends
        assert bool(ts.terminated[0, e]) == ends and not ts.truncated[0, e]
        # The reward of the terminal step follows the formula too: no penalty.
        ball_pos, ball_vel = ts.final_obs[0, e, 6:9].astype(np.float64), ts.final_obs[0, e, 9:12].astype(np.float64)
        reward = 1 / (1 + np.linalg.norm(ball_pos - [0, 0, 0.7])) / (1 + np.linalg.norm(ball_vel))
        np.testing.assert_allclose(ts.reward[0, e], reward, rtol=1e-5)


def test_resets_follow_the_documented_distribution(env):
    n = 4096
    states, ts = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), n))
    qpos, qvel = np.asarray(states.qpos, np.float64), np.asarray(states.qvel, np.float64)
    b, v = BALL_QPOS, BALL_DOF
    # The robot at rest, knee targets 0, the ball unturned and not spinning.
    np.testing.assert_allclose(qpos[:, :b], np.broadcast_to(env.mj_model.qpos0[:b], (n, b)), rtol=1e-7)
    np.testing.assert_array_equal(qvel[:, :v], 0.0)
    np.testing.assert_array_equal(states.target, 0.0)
    np.testing.assert_array_equal(qpos[:, b + 3 :], np.broadcast_to([1.0, 0.0, 0.0, 0.0], (n, 4)))
    np.testing.assert_array_equal(qvel[:, v + 3 :], 0.0)
    pos, vel = qpos[:, b : b + 3], qvel[:, v : v + 3]
    distance = np.linalg.norm(pos[:, :2], axis=1)
    assert 0.001 <= distance.min() < 0.005 and 0.495 < distance.max() <= 0.5
    assert abs(np.mean(distance) - 0.2505) < 0.01  # uniform, not uniform over the disc
    heading = np.arctan2(pos[:, 1], pos[:, 0])
    assert np.histogram(heading, 8, (-np.pi, np.pi))[0].min() > n / 8 * 0.85
    assert 1.0 <= pos[:, 2].min() < 1.01 and 1.99 < pos[:, 2].max() <= 2.0
    np.testing.assert_allclose(vel[:, 2], -5.0)
    # The horizontal velocity points at the axis, at speed ((d - 0.001) / 0.499) * U(0, 5).
    speed = np.linalg.norm(vel[:, :2], axis=1)
    toward = -np.sum(vel[:, :2] * pos[:, :2], axis=1) / distance
    np.testing.assert_allclose(toward, speed, atol=1e-5)
    scale = (distance - 0.001) / 0.499
    ratio = speed[scale > 0.1] / scale[scale > 0.1]
    assert ratio.min() >= 0.0 and 4.95 < ratio.max() <= 5.0 + 1e-4 and abs(ratio.mean() - 2.5) < 0.1
    # The first observation: robot at rest, the ball where it was put, the sensors' rest readings.
    obs = np.asarray(ts.obs)
    np.testing.assert_array_equal(obs[:, :6], 0.0)
    np.testing.assert_allclose(obs[:, 6:9], pos, rtol=1e-6)
    np.testing.assert_allclose(obs[:, 9:12], np.clip(vel, -5, 5), rtol=1e-6)
    np.testing.assert_allclose(obs[:, 12:], np.broadcast_to(env.rest_sensors, (n, 12)))
    np.testing.assert_allclose(obs[0, 12:15].sum(), 0.0, atol=1e-4)  # the legs' x-forces balance


# --------------------------------------------------------------------------------------------
# Under the vector wrappers


def test_tray_holds_its_height_and_the_ball_rests_until_truncation_at_500(resting):
    ts, states = resting
    assert not ts.terminated.any()
    for env_index in range(NUM_ENVS):
        np.testing.assert_array_equal(np.flatnonzero(ts.truncated[:, env_index]), [499])
    tray_height = states.qpos[:499, :, 2]
    assert np.abs(tray_height - bb.TRAY_HEIGHT).max() < 3e-3, tray_height.min()  # sags under 3 mm
    np.testing.assert_allclose(states.qpos[:499, :, 3], 1.0, atol=1e-4)  # and stays level
    ball = states.qpos[100:499, 0, BALL_QPOS : BALL_QPOS + 3]
    np.testing.assert_allclose(ball, np.broadcast_to([0, 0, REST_HEIGHT], ball.shape), atol=3e-3)
    np.testing.assert_allclose(ts.reward[100:499, 0], 1 / (1 + 0.7 - REST_HEIGHT), rtol=1e-2)
    # The step that truncates keeps its final observation and starts a new episode in obs.
    np.testing.assert_allclose(ts.final_obs[499, 0, 6:9], [0, 0, REST_HEIGHT], atol=3e-3)
    assert np.all((ts.obs[499, :, 8] >= 1.0) & (ts.obs[499, :, 8] <= 2.0))
    np.testing.assert_array_equal(ts.obs[499, :, :6], 0.0)


def test_sensors_carry_the_ball_weight(env, resting):
    ts, _ = resting
    m = env.mj_model
    tray_weight, ball_weight = m.body("tray").mass[0] * GRAVITY, m.body("ball").mass[0] * GRAVITY
    lifted = []
    for e, load in [(0, tray_weight + ball_weight), (1, tray_weight)]:
        info = pick(ts.info, 300, e)
        force, _ = bb.tray_loads(info["sensordata"], info["mount_xmat"], info["tray_xmat"])
        force = np.asarray(force)
        # In the tray's z axis the legs lift the tray and whatever lies on it, a third each;
        # sideways they cancel.
        np.testing.assert_allclose(force[:, 2].sum(), load, rtol=3e-3)
        np.testing.assert_allclose(force[:, 2], load / 3, rtol=1e-2)
        np.testing.assert_allclose(force[:, :2].sum(0), 0.0, atol=0.05)
        lifted.append(force[:, 2].sum())
        # The raw readings are in each site's frame: the same load, turned and of opposite sign.
        raw = info["sensordata"].reshape(2, 3, 3)[0]
        np.testing.assert_allclose(np.linalg.norm(raw, axis=1), np.linalg.norm(force, axis=1), rtol=1e-5)
    np.testing.assert_allclose(lifted[0] - lifted[1], ball_weight, rtol=1e-2)


def test_random_actions_stay_finite_and_episodes_restart(vector_env, rollout):
    actions = np.random.default_rng(2).uniform(-1.5, 1.5, (NUM_STEPS, NUM_ENVS, 3))
    ts, states = rollout(start(vector_env, 1), actions)
    for x in (ts.obs, ts.final_obs, ts.reward, states.qpos, states.qvel):
        assert np.all(np.isfinite(x))
    assert np.abs(ts.obs).max() <= 5.0 and np.all((ts.reward > 0.0) & (ts.reward <= 1.0))
    assert ts.terminated.sum() >= 2  # balls fell: episodes restarted
    ended = ts.terminated | ts.truncated
    assert np.all(ts.final_obs[ts.terminated][:, 8] < 0.15)
    np.testing.assert_array_equal(ts.obs[ended][:, :6], 0.0)  # a fresh episode's robot at rest
    np.testing.assert_array_equal(ts.obs[~ended], ts.final_obs[~ended])
    # The legs stay on their anchors' height range and the upper hinges near their limits:
    # MuJoCo's limits are soft, and random pushes of 1.5x full force take the hinges up to
    # 1.06 rad (45 degrees + 0.27) over ten trajectories measured (5 starts x 2 action seeds).
    assert np.abs(states.qpos[..., [k - 1 for k in KNEE_QPOS]]).max() < np.radians(45) + 0.35
    assert states.qpos[..., 2].min() > 0.15 and states.qpos[..., 2].max() < 0.85


# --------------------------------------------------------------------------------------------
# Training


def test_short_training_run_gives_finite_metrics(env):
    config = dataclasses.replace(
        PRESETS["isaacgym"], num_envs=8, num_steps=16, update_epochs=2, total_timesteps=8 * 16 * 2,
        hidden_sizes=(128, 64, 32), rpo_alpha=0.5,
    )  # fmt: skip
    state, metrics = jax.block_until_ready(jax.jit(make_train(config, env))(jax.random.PRNGKey(0)))
    for name, values in metric_arrays(metrics).items():
        assert values.shape[0] == 2 and np.all(np.isfinite(values)), name
    assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(state.params))
