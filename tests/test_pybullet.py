"""PyBullet's Ant and Minitaur on the host. Skipped without the `pybullet` extra."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from rpo_jax.run.records import metric_arrays
from rpo_jax import envs, ppo

pytest.importorskip("pybullet")
pytest.importorskip("gym")

from rpo_jax.config import Config
from rpo_jax.envs.pybullet import GYM_IDS, _import_pybullet_envs, _make_one  # noqa: E402


@pytest.mark.parametrize("name", sorted(GYM_IDS))
def test_steps_on_the_host_with_gyms_sizes_and_time_limit(name):
    gym = _import_pybullet_envs()
    reference = gym.spec(GYM_IDS[name])
    env = envs.make_vector_env(f"pybullet/{name}", 2)
    assert env.spec.max_episode_steps == reference.max_episode_steps == 1000
    probe = _make_one(GYM_IDS[name], 0, 0)  # as the suite builds one, keeping sys.path
    assert probe.observation_space.shape == (env.spec.observation_size,)
    assert probe.action_space.shape == (env.spec.action_size,)
    actions = jax.random.uniform(jax.random.PRNGKey(0), (10, 2, env.spec.action_size), minval=-1.0, maxval=1.0)

    def run(key):
        state, first = env.reset(key)
        return first, jax.lax.scan(env.step, state, actions)[1]

    first, traj = jax.jit(run)(jax.random.PRNGKey(1))
    assert first.obs.shape == (2, 28) and traj.obs.shape == (10, 2, 28)
    assert np.isfinite(traj.obs).all() and np.isfinite(traj.reward).all()
    assert (np.abs(np.asarray(traj.reward)) < 10).all()


@pytest.mark.slow
def test_ant_updates_to_finite_metrics():
    config = Config(num_envs=2, num_steps=32, num_minibatches=2, update_epochs=1, total_timesteps=128)
    _, metrics = jax.jit(ppo.make_train(config, envs.make_env("pybullet/Ant")))(jax.random.PRNGKey(0))
    for name, value in metric_arrays(metrics).items():
        assert np.isfinite(np.asarray(value)).all(), name
