"""Brax's policy as `--dist tanh-normal`: its log-probability and entropy estimate against Brax's own
`NormalTanhDistribution`, actions squashed onto the bounds, and the exports acting as `load_policy`."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.training.distribution import NormalTanhDistribution
from scipy import stats

from rpo_jax import envs, export, load_policy, ppo, train
from rpo_jax.config import MIN_SCALE, TANH_NORMAL, Config
from rpo_jax.errors import UsageError
from rpo_jax.networks import Actor, perturb_location, policy_distribution, policy_entropy, to_action

TINY = ["--num-envs", "8", "--num-steps", "16", "--num-minibatches", "2", "--update-epochs", "1", "--quiet"]


def brax_inputs(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Brax's policy parameters [16, 2 x 3] (location, then the scale's input) and pre-squash samples."""
    rng = np.random.default_rng(seed)
    params = (2 * rng.normal(size=(16, 6))).astype(np.float32)
    return params, (3 * rng.normal(size=(16, 3))).astype(np.float32)


def ours(params: np.ndarray) -> object:
    loc, scale_input = np.split(params, 2, axis=-1)
    return policy_distribution(jnp.asarray(loc), jnp.log(jax.nn.softplus(scale_input) + MIN_SCALE), TANH_NORMAL)


def test_log_prob_and_entropy_estimate_are_braxs():
    params, u = brax_inputs()
    brax = NormalTanhDistribution(3)
    dist = ours(params)
    # Scales down at the floor (1e-3) give log-probabilities near -1e6; Brax's form loses digits there.
    np.testing.assert_allclose(dist.log_prob(u), brax.log_prob(params, u), rtol=1e-5)
    key = jax.random.PRNGKey(3)
    np.testing.assert_allclose(policy_entropy(dist, key), brax.entropy(params, key), rtol=1e-5, atol=1e-5)
    # The estimate is of the squashed distribution: below the Gaussian's entropy, by the tanh's contraction.
    assert (np.asarray(policy_entropy(dist, key)) < np.asarray(dist.normal.entropy())).all()
    # A sample's log-probability is the one `sample_and_log_prob` returns, and Brax's for that sample.
    drawn, log_prob = dist.sample_and_log_prob(jax.random.PRNGKey(4))
    np.testing.assert_allclose(log_prob, brax.log_prob(params, np.asarray(drawn)), rtol=1e-5)


def test_the_state_dependent_scale_is_softplus_of_the_network_plus_the_floor():
    actor = Actor(3, (8,), "tanh", state_dependent_scale=True)
    obs = jax.random.normal(jax.random.PRNGKey(0), (5, 4))
    params = actor.init(jax.random.PRNGKey(1), obs[0])
    loc, log_scale = actor.apply(params, obs)
    assert loc.shape == log_scale.shape == (5, 3) and "log_std" not in params["params"]
    head = params["params"]["MLP_0"]["Dense_1"]
    assert head["kernel"].shape == (8, 6)
    # At the start the head's outputs are near 0: the scale near softplus(0) + 1e-3, varying with the state.
    np.testing.assert_allclose(np.exp(log_scale), np.log(2) + MIN_SCALE, atol=0.05)
    assert np.unique(np.asarray(log_scale)).size > 1


def test_rpo_perturbs_the_location_before_the_squash():
    params, u = brax_inputs(1)
    loc, scale_input = np.split(params, 2, axis=-1)
    perturbed = perturb_location(jnp.asarray(loc), jax.random.PRNGKey(2), 0.5)
    log_scale = jnp.log(jax.nn.softplus(scale_input) + MIN_SCALE)
    shifted = np.concatenate([np.asarray(perturbed), scale_input], axis=-1)
    np.testing.assert_allclose(
        policy_distribution(perturbed, log_scale, TANH_NORMAL).log_prob(u),
        NormalTanhDistribution(3).log_prob(shifted, u), rtol=1e-5,
    )  # fmt: skip


def test_actions_are_squashed_onto_the_bounds():
    u = jnp.asarray([[-30.0, 0.0, 0.5], [30.0, 2.0, -0.5]])
    low, high = jnp.asarray([-1.0, -2.0, 0.0]), jnp.asarray([1.0, 2.0, 4.0])
    action = np.asarray(to_action(u, TANH_NORMAL, low, high))
    np.testing.assert_allclose(action[:, 0], [-1, 1])  # saturated at the bounds
    np.testing.assert_allclose(action[:, 1], [0, 2 * np.tanh(2.0)], rtol=1e-6)
    np.testing.assert_allclose(action[:, 2], [2 + 2 * np.tanh(0.5), 2 - 2 * np.tanh(0.5)], rtol=1e-6)
    unit = jnp.ones(3)
    np.testing.assert_array_equal(to_action(u, TANH_NORMAL, -unit, unit), jnp.tanh(u))  # Brax's, exactly
    np.testing.assert_array_equal(to_action(u, "gaussian", low, high), u)  # the others: the environment clips


def test_training_steps_the_squashed_action_and_stores_the_sample():
    config = Config(algo="ppo", dist=TANH_NORMAL, num_envs=4, num_steps=8, num_minibatches=2, total_timesteps=32)
    trainer = ppo.make_trainer(config, envs.make_env("gym/Pendulum-v1"))
    state = trainer.init(jax.random.PRNGKey(0))
    original = trainer.env.step

    def step_reporting_the_action(env_state, action):  # the action the environment gets, as its reward
        env_state, ts = original(env_state, action)
        return env_state, ts.replace(reward=action[..., 0])

    object.__setattr__(trainer.env, "step", step_reporting_the_action)
    _, _, traj = jax.jit(lambda s: ppo.rollout(trainer, s.params, s.env_state, s.obs, s.key))(state)
    # Pendulum's bounds are [-2, 2]: the sample u stored, 2 tanh(u) stepped.
    np.testing.assert_allclose(traj.reward, 2 * np.tanh(np.asarray(traj.action[..., 0])), rtol=1e-6)
    assert np.unique(np.asarray(traj.reward)).size == traj.reward.size


def test_the_distribution_refuses_what_does_not_apply():
    with pytest.raises(UsageError, match="init_log_scale applies to the gaussian"):
        Config(dist=TANH_NORMAL, init_log_scale=-2.0).validate()
    unbounded = envs.EnvSpec("unbounded", 3, 1, (-np.inf,), (np.inf,), 10, "jax")
    with pytest.raises(UsageError, match="finite bounds"):
        ppo.make_networks(Config(dist=TANH_NORMAL), unbounded)


@pytest.fixture(scope="module")
def pendulum_run(tmp_path_factory):
    """A short tanh-normal run on Pendulum, whose actions lie in [-2, 2]: the squash's affine map is not the identity."""
    out = tmp_path_factory.mktemp("tanh") / "run"
    argv = ["--env", "gym/Pendulum-v1", "--dist", TANH_NORMAL, *TINY, "--total-timesteps", "512", "--hidden-sizes", "16", "8"]
    assert train.main([*argv, "--out", str(out)]) == 0
    return out


def test_exports_act_as_load_policy(pendulum_run, tmp_path):
    import onnx
    import onnxruntime

    onnx_path, npz_path = tmp_path / "policy.onnx", tmp_path / "policy.npz"
    assert export.main([str(pendulum_run), "--onnx", str(onnx_path), "--npz", str(npz_path)]) == 0
    arrays = dict(np.load(npz_path))
    assert str(arrays["distribution"]) == TANH_NORMAL and "log_std" not in arrays
    obs = np.random.default_rng(0).normal(size=(512, 3)).astype(np.float32) * np.array([1, 1, 8], np.float32)
    policy = load_policy(pendulum_run)
    expected = np.asarray(policy(obs, jax.random.PRNGKey(0), deterministic=True))
    np.testing.assert_allclose(export.forward(arrays, obs), expected, atol=1e-5)
    session = onnxruntime.InferenceSession(str(onnx_path))
    np.testing.assert_allclose(session.run(["action"], {"obs": obs})[0], expected, atol=1e-5)
    assert {prop.key: prop.value for prop in onnx.load(onnx_path).metadata_props} == {"distribution": TANH_NORMAL}
    # Many draws at one observation: the exported sampler's against the library's policy.
    one = np.tile(obs[:1], (20_000, 1))
    exported = export.sample(arrays, one, np.random.default_rng(1))[:, 0]
    library = np.asarray(policy(one, jax.random.PRNGKey(1), deterministic=False))[:, 0]
    assert stats.ks_2samp(exported, library).pvalue > 1e-3
    assert np.abs(library).max() <= 2 and np.unique(library).size > 1000
