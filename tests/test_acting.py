"""The policy that every consumer acts with: normalised observations, location or sample, bounds."""

import jax
import jax.numpy as jnp
import numpy as np

from rpo_jax import envs, ppo
from rpo_jax.acting import Policy
from rpo_jax.config import Config


def make_policy(config: Config) -> Policy:
    actor, _ = ppo.make_networks(config, envs.EnvSpec("acting", 3, 2, (-0.3,) * 2, (0.3,) * 2, 100, "jax"))
    params = actor.init(jax.random.PRNGKey(0), jnp.zeros(3))
    stats = envs.RunningMeanStd(mean=jnp.asarray([1.0, -2.0, 0.5]), var=jnp.asarray([4.0, 0.25, 1.0]), count=jnp.asarray(10.0))
    return Policy(config, actor, params, stats, jnp.full(2, -0.3), jnp.full(2, 0.3))


def test_the_deterministic_action_is_the_clipped_location_of_the_normalised_observation():
    config = Config(obs_clip=5.0)
    policy = make_policy(config)
    obs = jnp.asarray([[3.0, 100.0, -1.0], [0.0, 0.0, 0.0]])
    loc, _ = policy.actor.apply(policy.params, envs.normalize_observation(obs, policy.obs_stats, config.obs_clip))
    np.testing.assert_array_equal(policy(obs, jax.random.PRNGKey(1), deterministic=True), jnp.clip(loc, -0.3, 0.3))
    raw = make_policy(Config(normalize_obs=False))
    raw_loc, _ = raw.actor.apply(raw.params, obs)
    np.testing.assert_array_equal(raw(obs, jax.random.PRNGKey(1), deterministic=True), jnp.clip(raw_loc, -0.3, 0.3))


def test_a_policy_is_a_pytree_that_samples_within_the_bounds():
    policy = make_policy(Config(dist="laplace"))
    obs = jnp.ones((64, 3))
    act = jax.jit(lambda policy, obs, key: policy(obs, key, deterministic=False))
    actions = act(policy, obs, jax.random.PRNGKey(2))
    assert actions.shape == (64, 2) and bool(jnp.all(jnp.abs(actions) <= 0.3))
    sampled = policy(obs, jax.random.PRNGKey(2), deterministic=False)
    np.testing.assert_allclose(actions, sampled, rtol=1e-5, atol=1e-7)  # jit may fuse differently
    assert len(jax.tree.leaves(policy)) == len(jax.tree.leaves((policy.params, policy.obs_stats))) + 2
