"""Brax's own environments behind the same protocol as Cartpole."""

import jax
import numpy as np

from rpo_jax.run.records import metric_arrays
from rpo_jax import envs, ppo
from rpo_jax.config import Config


def test_brax_inverted_pendulum_updates_through_the_protocol_to_finite_metrics():
    env = envs.make_env("brax/inverted_pendulum")
    assert env.spec.name == "brax/inverted_pendulum" and env.spec.max_episode_steps == 1000
    assert (env.spec.observation_size, env.spec.action_size) == (4, 1)

    config = Config(num_envs=16, num_steps=32, num_minibatches=2, update_epochs=2, total_timesteps=16 * 32 * 3)
    state, metrics = jax.jit(ppo.make_train(config, env))(jax.random.PRNGKey(0))
    assert state.obs.shape == (16, 4)
    for name, value in metric_arrays(metrics).items():
        assert np.isfinite(np.asarray(value)).all(), name
    # A random policy drops the pendulum within tens of steps: episodes end and are reported
    # with Brax's reward of 1 per step, so the mean return equals the mean length.
    assert int(np.asarray(metrics.episodes_finished).sum()) > 0
    np.testing.assert_allclose(metrics.episode_return, metrics.episode_length, rtol=1e-5)


def test_brax_fluid_drag_gets_a_clip_that_takes_the_names_it_passes():
    # Brax 0.14.2's fluid drag (Swimmer's viscosity) calls jnp.clip(x, a_min=...), which JAX 0.10
    # removed: brax/swimmer raised a TypeError in every step. The slow check_env of every
    # registered environment steps Swimmer itself.
    from brax import fluid

    from rpo_jax.envs.brax import NUMPY_WITH_OLD_CLIP as jp

    x = jax.numpy.array([-1.0, 0.5, 2.0])
    np.testing.assert_array_equal(jp.clip(x, a_min=0.0), [0.0, 0.5, 2.0])
    np.testing.assert_array_equal(jp.clip(x, 0.0, 1.0), [0.0, 0.5, 1.0])
    assert jp.sqrt is jax.numpy.sqrt
    envs.make_env("brax/inverted_pendulum")
    assert fluid.jp is jp
