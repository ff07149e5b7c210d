"""The Gym suite: Pendulum-v1 in JAX against Gymnasium's own, BipedalWalker-v3 on the host.
Skipped without the `gym` extra (Gymnasium), which only the comparison and the walker need."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rpo_jax.run.records import metric_arrays
from rpo_jax import envs, ppo
from rpo_jax.config import Config

gymnasium = pytest.importorskip("gymnasium")

SMALL = Config(num_envs=4, num_steps=32, num_minibatches=2, update_epochs=1, total_timesteps=4 * 32 * 2, rpo_alpha=0.5)


def scan_steps(env, key, actions):
    """Resets a batched env and steps it through actions [T, N, act] in one jitted scan."""

    def run(key):
        state, first = env.reset(key)
        return first, jax.lax.scan(lambda s, a: env.step(s, a), state, actions)[1]

    return jax.jit(run)(key)


def test_pendulum_follows_gymnasium_from_the_same_start():
    pendulum = envs.make_env("gym/Pendulum-v1")
    state, first = pendulum.reset(jax.random.PRNGKey(3))
    reference = gymnasium.make("Pendulum-v1").unwrapped
    reference.reset(seed=0)
    reference.state = np.array([float(state.theta), float(state.theta_dot)])
    actions = 2.0 * np.sin(0.3 * np.arange(60))[:, None]
    step = jax.jit(pendulum.step)
    np.testing.assert_allclose(first.obs, reference._get_obs(), rtol=1e-5, atol=1e-6)
    for action in actions:
        state, ts = step(state, jnp.asarray(action, jnp.float32))
        obs, reward, terminated, truncated, _ = reference.step(action)
        np.testing.assert_allclose(ts.obs, obs, rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(ts.reward, reward, rtol=1e-4, atol=1e-4)
        assert not (ts.terminated or terminated or truncated)


def test_pendulum_is_truncated_at_200_steps_with_rewards_in_range():
    env = envs.make_vector_env("gym/Pendulum-v1", 3)
    assert env.spec.max_episode_steps == gymnasium.spec("Pendulum-v1").max_episode_steps == 200
    actions = jax.random.uniform(jax.random.PRNGKey(0), (400, 3, 1), minval=-2.0, maxval=2.0)
    first, traj = scan_steps(env, jax.random.PRNGKey(1), actions)
    assert first.obs.shape == (3, 3) and np.isfinite(traj.obs).all()
    truncated = np.asarray(traj.truncated)
    assert truncated[[199, 399]].all() and truncated.sum() == 6 and not np.asarray(traj.terminated).any()
    # The worst reward: angle pi, speed 8, torque 2.
    assert (np.asarray(traj.reward) <= 0).all() and (np.asarray(traj.reward) >= -(np.pi**2 + 0.1 * 64 + 0.004)).all()


def test_pendulum_updates_to_finite_metrics():
    _, metrics = jax.jit(ppo.make_train(SMALL, envs.make_env("gym/Pendulum-v1")))(jax.random.PRNGKey(0))
    for name, value in metric_arrays(metrics).items():
        assert np.isfinite(np.asarray(value)).all(), name


def test_bipedal_walker_steps_on_the_host():
    pytest.importorskip("Box2D")
    env = envs.make_vector_env("gym/BipedalWalker-v3", 2)
    reference = gymnasium.spec("BipedalWalker-v3")
    assert env.spec.max_episode_steps == reference.max_episode_steps == 1600
    probe = gymnasium.make("BipedalWalker-v3")
    assert probe.observation_space.shape == (env.spec.observation_size,)
    assert probe.action_space.shape == (env.spec.action_size,)
    actions = jax.random.uniform(jax.random.PRNGKey(0), (40, 2, 4), minval=-1.0, maxval=1.0)
    first, traj = scan_steps(env, jax.random.PRNGKey(1), actions)
    again = scan_steps(env, jax.random.PRNGKey(1), actions)[1]
    assert first.obs.shape == (2, 24) and traj.obs.shape == (40, 2, 24) and np.isfinite(traj.obs).all()
    # Per-step rewards: shaped progress, or -100 for a fall.
    assert ((np.asarray(traj.reward) > -101) & (np.asarray(traj.reward) < 10)).all()
    np.testing.assert_array_equal(traj.reward, again.reward)


@pytest.mark.slow
def test_bipedal_walker_updates_to_finite_metrics():
    pytest.importorskip("Box2D")
    _, metrics = jax.jit(ppo.make_train(SMALL, envs.make_env("gym/BipedalWalker-v3")))(jax.random.PRNGKey(0))
    for name, value in metric_arrays(metrics).items():
        assert np.isfinite(np.asarray(value)).all(), name
