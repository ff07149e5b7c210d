"""Cartpole on MJX, the vector environment and the wrappers training puts around it."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

from rpo_jax.envs import (
    ClipAction,
    EnvSpec,
    EpisodeStatistics,
    NormalizeObservation,
    NormalizeReward,
    TimeLimit,
    TimeStep,
    VectorEnv,
    make_env,
    make_vector_env,
)
from rpo_jax.envs.cartpole import Cartpole, CartpoleState
from rpo_jax.envs.wrappers import TimeLimitState


@pytest.fixture(scope="module")
def cartpole():
    return Cartpole()


@pytest.fixture(scope="module")
def step(cartpole):
    # One compiled single-environment step, shared by every test that steps a CartpoleState.
    return jax.jit(cartpole.step)


def cart_state(x, angle, x_dot, angle_dot):
    return CartpoleState(qpos=jnp.array([x, angle], jnp.float32), qvel=jnp.array([x_dot, angle_dot], jnp.float32))


def expected_obs(state):
    qpos, qvel = np.asarray(state.qpos), np.asarray(state.qvel)
    return np.clip([qpos[0], qvel[0], qpos[1], qvel[1]], -5.0, 5.0)


def expected_reward(state):
    x, angle = np.asarray(state.qpos, np.float64)
    x_dot, angle_dot = np.asarray(state.qvel, np.float64)
    return 1.0 - angle**2 - 0.01 * abs(x_dot) - 0.005 * abs(angle_dot)


# --------------------------------------------------------------------------------------------
# Cartpole itself


def test_spec():
    spec = Cartpole.spec
    assert (spec.name, spec.observation_size, spec.action_size) == ("cartpole", 4, 1)
    assert (spec.action_low, spec.action_high, spec.max_episode_steps) == ((-1.0,), (1.0,), 500)


def test_observation_layout_and_reward_formula_along_a_trajectory(cartpole, step):
    state, ts = jax.jit(cartpole.reset)(jax.random.PRNGKey(0))
    np.testing.assert_array_equal(ts.obs, expected_obs(state))
    np.testing.assert_array_equal(ts.final_obs, ts.obs)
    assert float(ts.reward) == 0 and not ts.terminated and not ts.truncated

    actions = jax.random.uniform(jax.random.PRNGKey(1), (10, 1), minval=-1, maxval=1)
    for action in actions:
        previous = state
        state, ts = step(state, action)
        assert not np.array_equal(state.qpos, previous.qpos)  # it really moved
        assert not ts.terminated and not ts.truncated
        np.testing.assert_array_equal(ts.obs, expected_obs(state))
        np.testing.assert_array_equal(ts.final_obs, ts.obs)
        np.testing.assert_allclose(ts.reward, expected_reward(state), rtol=1e-6, atol=1e-6)


def test_observation_is_clipped_to_plus_minus_5(step):
    state, ts = step(cart_state(0.0, 0.0, 9.0, -12.0), jnp.zeros(1))
    assert abs(float(state.qvel[0])) > 5 and abs(float(state.qvel[1])) > 5  # beyond the clip
    np.testing.assert_array_equal(ts.obs, expected_obs(state))
    assert ts.obs[1] == 5.0 and ts.obs[3] == -5.0


def test_action_is_clipped_to_bounds_by_the_environment(step):
    start = cart_state(0.0, 0.05, 0.1, -0.1)
    for outside, bound in [(3.0, 1.0), (-7.0, -1.0)]:
        beyond, at_bound = step(start, jnp.array([outside])), step(start, jnp.array([bound]))
        for a, b in zip(jax.tree.leaves(beyond), jax.tree.leaves(at_bound), strict=True):
            np.testing.assert_array_equal(a, b)
    # ...while an action inside the bounds does push the cart differently.
    assert not np.array_equal(step(start, jnp.array([0.5]))[0].qvel, step(start, jnp.array([1.0]))[0].qvel)


@pytest.mark.parametrize(
    "start, action",
    [
        ((2.999, 0.0, 5.0, 0.0), 1.0),  # cart leaves x > 3
        ((-2.999, 0.0, -5.0, 0.0), -1.0),  # cart leaves x < -3
        ((0.0, 1.57, 0.0, 3.0), 0.0),  # pole falls past pi/2
        ((0.0, -1.57, 0.0, -3.0), 0.0),  # pole falls past -pi/2
    ],
)
def test_leaving_the_bounds_terminates_with_reward_minus_2(step, start, action):
    state, ts = step(cart_state(*start), jnp.array([action]))
    x, angle = np.asarray(state.qpos)
    assert abs(x) > 3 or abs(angle) > np.pi / 2
    assert bool(ts.terminated) and not bool(ts.truncated)
    assert float(ts.reward) == -2.0


@pytest.mark.parametrize("start", [(2.9, 0.0, 0.0, 0.0), (0.0, 1.5, 0.0, 0.0), (-2.95, -1.4, 0.5, 0.5)])
def test_safe_state_near_the_bounds_does_not_terminate(step, start):
    state, ts = step(cart_state(*start), jnp.zeros(1))
    assert not bool(ts.terminated)
    np.testing.assert_allclose(ts.reward, expected_reward(state), rtol=1e-6, atol=1e-6)


def test_resets_are_uniform_over_the_documented_ranges(cartpole):
    states, ts = jax.jit(jax.vmap(cartpole.reset))(jax.random.split(jax.random.PRNGKey(0), 4096))
    qpos, qvel = np.asarray(states.qpos), np.asarray(states.qvel)
    for values, bound in [(qpos, 0.1), (qvel, 0.25)]:
        assert values.shape == (4096, 2)
        assert values.min() >= -bound and values.max() <= bound
        # With 4096 uniform draws the extremes lie within 2.5% of the bounds.
        assert np.all(values.min(0) < -0.975 * bound) and np.all(values.max(0) > 0.975 * bound)
        assert abs(np.corrcoef(values[:, 0], values[:, 1])[0, 1]) < 0.1  # independent joints
    np.testing.assert_array_equal(ts.obs, np.stack([qpos[:, 0], qvel[:, 0], qpos[:, 1], qvel[:, 1]], -1))


def test_time_limit_truncates_balanced_cartpole_at_step_500(cartpole):
    # The upright pole at rest with zero force is an exact equilibrium: it never terminates.
    env = TimeLimit(cartpole)
    state = TimeLimitState(cart_state(0.0, 0.0, 0.0, 0.0), jnp.zeros((), jnp.int32))

    @jax.jit
    def run(state):
        return jax.lax.scan(lambda s, _: env.step(s, jnp.zeros(1)), state, None, length=500)

    final_state, ts = run(state)
    np.testing.assert_array_equal(final_state.inner.qpos, [0.0, 0.0])
    np.testing.assert_array_equal(final_state.inner.qvel, [0.0, 0.0])
    assert not ts.terminated.any()
    np.testing.assert_array_equal(np.flatnonzero(ts.truncated), [499])
    np.testing.assert_allclose(ts.reward, 1.0)


@pytest.fixture(scope="module")
def one_cartpole(cartpole):
    return VectorEnv(cartpole, 1)


@pytest.fixture(scope="module")
def auto_reset_step(one_cartpole):
    return jax.jit(one_cartpole.step)


def _auto_reset_state(one_cartpole, cart, elapsed):
    """One environment at `cart`, `elapsed` steps into its episode, with a fresh pool of starts."""
    state, _ = one_cartpole.reset(jax.random.PRNGKey(7))
    batched = jax.tree.map(lambda x: jnp.asarray(x)[None], TimeLimitState(cart, jnp.asarray(elapsed, jnp.int32)))
    return state.replace(envs=batched)


def _assert_fresh_episode(new_state, ts):
    inner = jax.tree.map(lambda x: x[0], new_state.envs)
    assert int(inner.elapsed) == 0
    np.testing.assert_array_equal(ts.obs[0], expected_obs(inner.inner))
    np.testing.assert_array_equal(ts.obs[0], new_state.start_obs[0])  # the pool's start, taken
    assert np.all(np.abs(np.asarray(inner.inner.qpos)) <= 0.1)
    assert np.all(np.abs(np.asarray(inner.inner.qvel)) <= 0.25)


def test_auto_reset_after_termination_keeps_terminal_observation(one_cartpole, auto_reset_step):
    state = _auto_reset_state(one_cartpole, cart_state(2.999, 0.0, 5.0, 0.0), 10)
    new_state, ts = auto_reset_step(state, jnp.ones((1, 1)))
    assert bool(ts.terminated[0]) and not bool(ts.truncated[0])
    assert float(ts.reward[0]) == -2.0  # the reward of the step that ended the episode
    assert float(ts.final_obs[0, 0]) > 3.0  # terminal cart position
    _assert_fresh_episode(new_state, ts)


def test_auto_reset_after_truncation_keeps_flag_and_final_observation(one_cartpole, auto_reset_step):
    start = cart_state(0.5, 0.0, 0.0, 0.0)
    new_state, ts = auto_reset_step(_auto_reset_state(one_cartpole, start, 499), jnp.zeros((1, 1)))
    assert bool(ts.truncated[0]) and not bool(ts.terminated[0])
    assert float(ts.final_obs[0, 0]) == pytest.approx(0.5, abs=1e-6)  # where the old episode stood
    assert float(ts.reward[0]) == pytest.approx(1.0, abs=1e-6)
    _assert_fresh_episode(new_state, ts)
    # One step earlier the episode just continues.
    cont_state, ts = auto_reset_step(_auto_reset_state(one_cartpole, start, 498), jnp.zeros((1, 1)))
    assert not bool(ts.truncated[0]) and int(cont_state.envs.elapsed[0]) == 499
    np.testing.assert_array_equal(ts.obs, ts.final_obs)


def test_vector_env_stays_finite_and_in_bounds_under_jit_and_scan():
    env = make_vector_env("cartpole", 64)

    @jax.jit
    def run(key):
        state, _ = env.reset(key)
        actions = jax.random.uniform(key, (200, 64, 1), minval=-3.0, maxval=3.0)  # beyond bounds
        return jax.lax.scan(env.step, state, actions)

    _, ts = run(jax.random.PRNGKey(0))
    assert ts.obs.shape == ts.final_obs.shape == (200, 64, 4) and ts.reward.shape == (200, 64)
    for x in (ts.obs, ts.final_obs, ts.reward):
        assert np.all(np.isfinite(x))
    assert np.abs(np.asarray(ts.obs)).max() <= 5.0 and np.abs(np.asarray(ts.final_obs)).max() <= 5.0
    assert np.all((np.asarray(ts.reward) >= -2.0) & (np.asarray(ts.reward) <= 1.0))
    assert ts.terminated.any()  # random pushes of full force end episodes: resets were exercised
    np.testing.assert_array_equal(np.asarray(ts.reward)[np.asarray(ts.terminated)], -2.0)


def test_make_env_rejects_unknown_name_and_points_at_the_listing():
    with pytest.raises(ValueError, match="unknown env 'nope'") as info:
        make_env("nope")
    assert "python -m rpo_jax.envs lists them" in str(info.value)
    assert isinstance(make_env("cartpole"), Cartpole)


# --------------------------------------------------------------------------------------------
# Wrappers, on a tiny pure-JAX stand-in environment (no physics, nothing slow to compile)


@struct.dataclass
class FakeState:
    count: jax.Array  # steps into the episode
    length: jax.Array  # the episode terminates after this many steps
    key: jax.Array


class FakeEnv:
    """Counts steps. obs = [count, noise] (noise ~ N(3, 2)), reward = count * 0.5 + action.
    Reset draws obs [-1 - u, noise], u in [0, 1), and an episode length in [min_len, max_len]."""

    def __init__(self, max_episode_steps=1000, min_len=1000, max_len=1000):
        self.spec = EnvSpec("fake", 2, 1, (-1.0,), (1.0,), max_episode_steps, "test")
        self.min_len, self.max_len = min_len, max_len

    def _obs(self, first, key):
        return jnp.stack([first, 3.0 + 2.0 * jax.random.normal(key)])

    def reset(self, key):
        k_len, k_obs, k_state = jax.random.split(key, 3)
        length = jax.random.randint(k_len, (), self.min_len, self.max_len + 1)
        obs = self._obs(-1.0 - jax.random.uniform(k_obs), k_obs)
        return FakeState(jnp.zeros((), jnp.int32), length, k_state), TimeStep(
            obs, jnp.zeros(()), jnp.zeros((), bool), jnp.zeros((), bool), obs
        )

    def step(self, state, action):
        key, k_obs = jax.random.split(state.key)
        count = state.count + 1
        obs = self._obs(count.astype(jnp.float32), k_obs)
        terminated = count >= state.length
        reward = 0.5 * count + action[0]
        return FakeState(count, state.length, key), TimeStep(obs, reward, terminated, jnp.zeros((), bool), obs)


@pytest.mark.parametrize("terminate_at", [None, 5])
def test_time_limit_and_auto_reset_on_fake_env(terminate_at):
    length = 1000 if terminate_at is None else terminate_at
    env = VectorEnv(FakeEnv(max_episode_steps=5, min_len=length, max_len=length), 1)
    state, _ = env.reset(jax.random.PRNGKey(0))
    step = jax.jit(env.step)
    for t in range(1, 13):
        state, ts = step(state, jnp.zeros((1, 1)))
        ts = jax.tree.map(lambda x: x[0], ts)
        in_episode = (t - 1) % 5 + 1
        ended = in_episode == 5
        # At step 5 the time limit is reached; if the env terminated that very step, it is a
        # termination and not a truncation.
        assert bool(ts.truncated) == (ended and terminate_at is None), t
        assert bool(ts.terminated) == (ended and terminate_at is not None), t
        assert float(ts.final_obs[0]) == in_episode  # the observation the step reached
        if ended:
            assert -2.0 < float(ts.obs[0]) <= -1.0  # a fresh episode's first observation
            assert int(state.envs.elapsed[0]) == 0 and int(state.envs.inner.count[0]) == 0
        else:
            np.testing.assert_array_equal(ts.obs, ts.final_obs)
            assert int(state.envs.elapsed[0]) == in_episode


def test_episode_statistics_report_undiscounted_return_and_length_at_episode_end():
    num_envs = 3
    env = EpisodeStatistics(VectorEnv(FakeEnv(min_len=2, max_len=6), num_envs))
    state, _ = env.reset(jax.random.PRNGKey(1))
    step = jax.jit(env.step)
    actions = jax.random.uniform(jax.random.PRNGKey(2), (30, num_envs, 1), minval=-1, maxval=1)
    running_return, running_length, finished = np.zeros(num_envs), np.zeros(num_envs, int), 0
    for action in actions:
        state, ts = step(state, action)
        running_return += np.asarray(ts.reward)
        running_length += 1
        done = np.asarray(ts.terminated | ts.truncated)
        np.testing.assert_allclose(ts.info["episode_return"], np.where(done, running_return, 0.0), rtol=1e-5)
        np.testing.assert_array_equal(ts.info["episode_length"], np.where(done, running_length, 0))
        running_return[done], running_length[done] = 0.0, 0
        finished += done.sum()
    assert finished >= 10  # episodes of 2..6 steps: many ended, of several lengths


def test_clip_action_clips_to_spec_bounds():
    env = ClipAction(VectorEnv(FakeEnv(), 4))
    state, _ = env.reset(jax.random.PRNGKey(0))
    _, ts = env.step(state, jnp.array([[-3.0], [-0.25], [0.75], [3.0]]))
    # reward = 0.5 * 1 + the action the simulator received
    np.testing.assert_allclose(ts.reward, 0.5 + np.array([-1.0, -0.25, 0.75, 1.0]))


def test_normalize_observation_tracks_batch_mean_and_variance():
    num_envs, clip = 16, 1.5
    inner = VectorEnv(FakeEnv(), num_envs)
    env = NormalizeObservation(inner, clip=clip)
    state, ts = env.reset(jax.random.PRNGKey(0))
    _, raw = inner.reset(jax.random.PRNGKey(0))
    seen = [np.asarray(raw.obs)]
    for _ in range(20):
        action = jnp.zeros((num_envs, 1))
        _, raw = inner.step(state.inner, action)  # what the wrapper sees underneath
        state, ts = env.step(state, action)
        seen.append(np.asarray(raw.obs))
    seen = np.concatenate(seen).astype(np.float64)
    mean, var = seen.mean(0), seen.var(0)
    np.testing.assert_allclose(state.obs_stats.mean, mean, rtol=1e-3, atol=1e-3)
    np.testing.assert_allclose(state.obs_stats.var, var, rtol=1e-3, atol=1e-3)
    expected = np.clip((np.asarray(raw.obs) - mean) / np.sqrt(var + 1e-8), -clip, clip)
    np.testing.assert_allclose(ts.obs, expected, rtol=1e-3, atol=1e-3)
    assert np.any(np.abs(expected) == clip)  # the clip is exercised
    # Disabled: observations pass through untouched.
    off = NormalizeObservation(inner, clip=clip, enabled=False)
    off_state, off_ts = off.reset(jax.random.PRNGKey(0))
    _, off_ts = off.step(off_state, jnp.zeros((num_envs, 1)))
    _, raw = inner.step(off_state.inner, jnp.zeros((num_envs, 1)))
    np.testing.assert_array_equal(off_ts.obs, raw.obs)


@pytest.mark.parametrize("normalize", [True, False])
def test_normalize_reward_scales_divides_by_return_std_and_clips(normalize):
    num_envs, gamma, clip, scale = 8, 0.9, 1.2, 2.0
    inner = EpisodeStatistics(VectorEnv(FakeEnv(min_len=3, max_len=8), num_envs))
    env = NormalizeReward(inner, gamma=gamma, clip=clip, scale=scale, normalize=normalize)
    state, _ = env.reset(jax.random.PRNGKey(3))
    actions = jax.random.uniform(jax.random.PRNGKey(4), (25, num_envs, 1), minval=-1, maxval=1)
    discounted, history, clipped = np.zeros(num_envs), [], 0
    for action in actions:
        _, raw = inner.step(state.inner, action)
        state, ts = env.step(state, action)
        reward = scale * np.asarray(raw.reward, np.float64)
        discounted = gamma * discounted + reward
        history.append(discounted.copy())
        if normalize:
            std = np.concatenate(history).std()
            expected = np.clip(reward / std, -clip, clip)
            clipped += np.sum(np.abs(expected) == clip)
        else:
            expected = reward
        np.testing.assert_allclose(ts.reward, expected, rtol=2e-3, atol=1e-5)
        discounted[np.asarray(raw.terminated | raw.truncated)] = 0.0
    if normalize:
        assert 0 < clipped < actions.shape[0] * num_envs  # the clip binds sometimes, not always
