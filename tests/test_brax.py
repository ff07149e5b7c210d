"""Brax's own environments behind the same protocol as Cartpole."""

import jax
import numpy as np

from rpo_jax import envs, ppo
from rpo_jax.config import Config


def test_brax_inverted_pendulum_trains_through_the_protocol():
    env = envs.make_env("brax/inverted_pendulum")
    assert env.spec.name == "brax/inverted_pendulum" and env.spec.max_episode_steps == 1000
    assert (env.spec.observation_size, env.spec.action_size) == (4, 1)

    config = Config(num_envs=16, num_steps=32, num_minibatches=2, update_epochs=2, total_timesteps=16 * 32 * 3)
    state, metrics = jax.jit(ppo.make_train(config, env))(jax.random.PRNGKey(0))
    assert state.obs.shape == (16, 4)
    for name, value in vars(metrics).items():
        assert np.isfinite(np.asarray(value)).all(), name
    # A random policy drops the pendulum within tens of steps: episodes end and are reported
    # with Brax's reward of 1 per step, so the mean return equals the mean length.
    assert int(np.asarray(metrics.episodes_finished).sum()) > 0
    np.testing.assert_allclose(metrics.episode_return, metrics.episode_length, rtol=1e-5)
