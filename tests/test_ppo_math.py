"""The maths of PPO/RPO: GAE, the RPO perturbation, the loss, the Gaussian policy, Config checks."""

from __future__ import annotations

import collections
import dataclasses
import itertools
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats

from rpo_jax import cpu_workarounds, envs
from rpo_jax import loss as loss_module
from rpo_jax import ppo
from rpo_jax.config import Config
from rpo_jax.envs.recipes import PRESETS
from rpo_jax.envs import make_env
from rpo_jax.loss import Batch, compute_gae, ppo_loss
from rpo_jax.networks import perturb_location, policy_distribution
from rpo_jax.ppo import make_networks, make_trainer

# --------------------------------------------------------------------------------------------
# GAE


def reference_gae(rewards, values, next_values, terminated, truncated, gamma, gae_lambda):
    """The textbook recursion as a plain double loop, in float64."""
    T, N = rewards.shape
    advantages = np.zeros((T, N))
    for n in range(N):
        next_advantage = 0.0
        for t in reversed(range(T)):
            delta = rewards[t, n] + gamma * next_values[t, n] * (1 - terminated[t, n]) - values[t, n]
            ended = terminated[t, n] or truncated[t, n]
            next_advantage = delta + gamma * gae_lambda * (1 - ended) * next_advantage
            advantages[t, n] = next_advantage
    return advantages, advantages + values


def test_compute_gae_matches_python_double_loop_with_terminations_and_truncations():
    rng = np.random.default_rng(0)
    T, N = 17, 5
    rewards = rng.normal(size=(T, N)).astype(np.float32)
    values = rng.normal(size=(T, N)).astype(np.float32)
    next_values = rng.normal(size=(T, N)).astype(np.float32)
    terminated = rng.random((T, N)) < 0.2
    truncated = rng.random((T, N)) < 0.2
    # The data must exercise every combination of the two flags, or the comparison proves little.
    for term, trunc in [(0, 0), (1, 0), (0, 1), (1, 1)]:
        assert ((terminated == term) & (truncated == trunc)).any()

    gamma, gae_lambda = 0.97, 0.9
    advantages, returns = compute_gae(
        jnp.asarray(rewards), jnp.asarray(values), jnp.asarray(next_values),
        jnp.asarray(terminated), jnp.asarray(truncated), gamma, gae_lambda,
    )  # fmt: skip
    expected_adv, expected_ret = reference_gae(
        rewards.astype(np.float64), values.astype(np.float64), next_values.astype(np.float64),
        terminated, truncated, gamma, gae_lambda,
    )  # fmt: skip
    assert advantages.shape == returns.shape == (T, N)
    np.testing.assert_allclose(advantages, expected_adv, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(returns, expected_ret, rtol=1e-5, atol=1e-5)


def cleanrl_gae(rewards, values, next_value, dones, next_done, gamma, gae_lambda):
    """CleanRL's ppo_continuous_action.py loop, as the paper ran it. `dones[t]` marks that the
    observation at t starts an episode (the step before it ended one, by termination or time
    limit alike); `values[t]` is that observation's value."""
    T = rewards.shape[0]
    advantages = np.zeros_like(rewards)
    lastgaelam = 0
    for t in reversed(range(T)):
        if t == T - 1:
            nextnonterminal, nextvalues = 1.0 - next_done, next_value
        else:
            nextnonterminal, nextvalues = 1.0 - dones[t + 1], values[t + 1]
        delta = rewards[t] + gamma * nextvalues * nextnonterminal - values[t]
        advantages[t] = lastgaelam = delta + gamma * gae_lambda * nextnonterminal * lastgaelam
    return advantages, advantages + values


def test_terminate_handling_is_cleanrls_gae():
    rng = np.random.default_rng(1)
    T, N = 23, 6
    rewards = rng.normal(size=(T, N))
    values = rng.normal(size=(T + 1, N))  # the value of every observation, the one after the last step too
    terminated, truncated = rng.random((T, N)) < 0.15, rng.random((T, N)) < 0.15
    ended = terminated | truncated
    assert terminated.any() and truncated.any() and (~ended).any()
    # Where an episode ended, the value of the observation it reached differs from that of the
    # next episode's first one, which CleanRL's loop never reads there.
    next_values = np.where(ended, rng.normal(size=(T, N)), values[1:])
    gamma, gae_lambda = 0.99, 0.95
    advantages, returns = compute_gae(
        *(jnp.asarray(x, jnp.float32) for x in (rewards, values[:-1], next_values)),
        jnp.asarray(terminated), jnp.asarray(truncated), gamma, gae_lambda, "terminate",
    )  # fmt: skip
    dones = np.concatenate([np.zeros((1, N)), ended[:-1]]).astype(float)
    for n in range(N):
        expected_adv, expected_ret = cleanrl_gae(
            rewards[:, n], values[:-1, n], values[-1, n], dones[:, n], float(ended[-1, n]), gamma, gae_lambda
        )
        np.testing.assert_allclose(advantages[:, n], expected_adv, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(returns[:, n], expected_ret, rtol=1e-5, atol=1e-5)
    bootstrapped, _ = compute_gae(
        *(jnp.asarray(x, jnp.float32) for x in (rewards, values[:-1], next_values)),
        jnp.asarray(terminated), jnp.asarray(truncated), gamma, gae_lambda, "bootstrap",
    )  # fmt: skip
    assert not np.allclose(bootstrapped, advantages)  # the handlings differ exactly at truncations
    np.testing.assert_array_equal(np.isclose(bootstrapped, advantages, atol=1e-6).all(axis=0), ~truncated.any(axis=0))


def _gae(rewards, values, next_values, terminated, truncated, gamma=0.5, gae_lambda=0.5):
    # Single-environment columns [T] -> [T, 1]. Inputs are dyadic, so float32 results are exact.
    col = lambda x, dtype=jnp.float32: jnp.asarray(x, dtype)[:, None]  # noqa: E731
    adv, ret = compute_gae(
        col(rewards), col(values), col(next_values), col(terminated, bool), col(truncated, bool),
        gamma, gae_lambda,
    )  # fmt: skip
    return np.asarray(adv)[:, 0], np.asarray(ret)[:, 0]


@pytest.mark.parametrize("final_value", [2.0, 6.0])
def test_truncated_step_bootstraps_from_final_observation_value(final_value):
    # delta = r + gamma * V(final_obs) - V(obs) = 1 + 0.5 * final_value - 0.5
    adv, ret = _gae([1.0], [0.5], [final_value], [False], [True])
    np.testing.assert_array_equal(adv, [0.5 + 0.5 * final_value])
    np.testing.assert_array_equal(ret, [1.0 + 0.5 * final_value])


@pytest.mark.parametrize("final_value", [2.0, 6.0, -100.0])
def test_terminated_step_ignores_next_value(final_value):
    adv, ret = _gae([1.0], [0.5], [final_value], [True], [False])
    np.testing.assert_array_equal(adv, [0.5])  # r - V(obs), whatever next_values says
    np.testing.assert_array_equal(ret, [1.0])


def test_episode_end_cuts_advantage_recursion_but_continuing_step_chains():
    # Step 0 continues into step 1: A0 = delta0 + gamma*lambda*A1, and delta0 bootstraps from
    # next_values[0]. Step 1 is truncated: A1 = r1 + gamma*next_values[1] - V1.
    adv, _ = _gae([1.0, 2.0], [0.5, 1.0], [1.0, 4.0], [False, False], [False, True])
    a1 = 2.0 + 0.5 * 4.0 - 1.0  # 3
    a0 = (1.0 + 0.5 * 1.0 - 0.5) + 0.25 * a1  # 1.75
    np.testing.assert_array_equal(adv, [a0, a1])

    # Now step 0 is itself truncated (an auto-reset sits between the steps): its advantage
    # bootstraps from its own final observation (next_values[0] = 8) and ignores step 1.
    adv, _ = _gae([1.0, 2.0], [0.5, 1.0], [8.0, 4.0], [False, False], [True, True])
    np.testing.assert_array_equal(adv, [1.0 + 0.5 * 8.0 - 0.5, 2.0 + 0.5 * 4.0 - 1.0])

    # Terminated at step 0: no bootstrap and no recursion.
    adv, _ = _gae([1.0, 2.0], [0.5, 1.0], [8.0, 4.0], [True, False], [False, True])
    np.testing.assert_array_equal(adv, [0.5, 3.0])


@pytest.mark.parametrize(("truncation", "with_truncations"), [("bootstrap", True), ("bootstrap", False), ("terminate", True)])
def test_make_batch_reads_each_final_observation_that_gae_reads(truncation, with_truncations):
    # make_batch takes a step's next value from the following step's observation and runs the
    # critic over the final observations only when a truncation bootstraps from them. Where an
    # episode ended, the final observation differs from the next one (an auto-reset sits
    # between), so reading the wrong one changes the advantages.
    T, N = 6, 5
    config = Config(num_envs=N, num_steps=T, num_minibatches=1, truncation=truncation)
    trainer = make_trainer(config, make_env("cartpole"))
    state = trainer.init(jax.random.PRNGKey(0))
    rng = np.random.default_rng(1)
    obs = rng.normal(size=(T + 1, N, 4)).astype(np.float32)
    terminated = rng.random((T, N)) < 0.2
    truncated = (rng.random((T, N)) < 0.3) & ~terminated & with_truncations
    assert truncated.any() == with_truncations and terminated.any()
    ended = terminated | truncated
    final_obs = np.where(ended[..., None], rng.normal(size=(T, N, 4)).astype(np.float32), obs[1:])
    zeros = jnp.zeros((T, N))
    traj = ppo.Transition(
        jnp.asarray(obs[:-1]), jnp.asarray(final_obs), jnp.zeros((T, N, 1)), zeros,
        jnp.asarray(rng.normal(size=(T, N)), jnp.float32), jnp.asarray(terminated), jnp.asarray(truncated),
        zeros, zeros, {},
    )  # fmt: skip
    batch, _ = jax.jit(lambda t: ppo.make_batch(trainer, state.params, t, state.value_stats))(traj)
    critic = lambda x: trainer.critic.apply(state.params["critic"], jnp.asarray(x))  # noqa: E731
    advantages, returns = compute_gae(
        traj.reward, critic(obs[:-1]), critic(final_obs), traj.terminated, traj.truncated,
        config.gamma, config.gae_lambda, truncation,
    )  # fmt: skip
    np.testing.assert_allclose(batch.advantages, advantages.reshape(-1), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(batch.returns, returns.reshape(-1), rtol=1e-6, atol=1e-6)


# --------------------------------------------------------------------------------------------
# The Gaussian policy and RPO's perturbation


@pytest.mark.parametrize("log_scale_shape", [(8, 3), (3,)])  # per sample, and the actor's [action_size]
def test_policy_log_prob_and_entropy_match_closed_form_and_scipy(log_scale_shape):
    rng = np.random.default_rng(1)
    loc = rng.normal(size=(8, 3)).astype(np.float32)
    log_scale = rng.uniform(-1.5, 1.0, size=log_scale_shape).astype(np.float32)
    actions = (loc + rng.normal(size=(8, 3)) * 2).astype(np.float32)
    dist = policy_distribution(jnp.asarray(loc), jnp.asarray(log_scale))

    sigma = np.exp(np.broadcast_to(log_scale.astype(np.float64), (8, 3)))
    mu = loc.astype(np.float64)
    closed_log_prob = (-0.5 * ((actions - mu) / sigma) ** 2 - np.log(sigma) - 0.5 * np.log(2 * np.pi)).sum(-1)
    closed_entropy = (0.5 + 0.5 * np.log(2 * np.pi) + np.log(sigma)).sum(-1)

    log_prob, entropy = np.asarray(dist.log_prob(jnp.asarray(actions))), np.asarray(dist.entropy())
    assert log_prob.shape == entropy.shape == (8,)  # summed over action dimensions
    np.testing.assert_allclose(log_prob, closed_log_prob, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(entropy, closed_entropy, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(log_prob, scipy.stats.norm.logpdf(actions, mu, sigma).sum(-1), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(entropy, scipy.stats.norm.entropy(mu, sigma).sum(-1), rtol=1e-5, atol=1e-5)


# --------------------------------------------------------------------------------------------
# The epochs' shuffle


@pytest.mark.parametrize("n", [1, 2, 3, 64, 1000, 2048, 2049, 131072])
def test_shuffled_indices_is_a_permutation_drawn_from_the_key(n):
    drawn = np.asarray(cpu_workarounds.shuffled_indices(jax.random.PRNGKey(0), n))
    assert drawn.dtype == np.int32
    np.testing.assert_array_equal(np.sort(drawn), np.arange(n))
    np.testing.assert_array_equal(drawn, cpu_workarounds.shuffled_indices(jax.random.PRNGKey(0), n))
    if n > 3:
        assert not np.array_equal(drawn, cpu_workarounds.shuffled_indices(jax.random.PRNGKey(1), n))


def one_round_of_two_random_bits(key, n):
    """A shuffle with too few random bits: indices whose bits tie keep their order."""
    index_bits = (n - 1).bit_length()
    packed = (jax.random.bits(key, (n,), jnp.uint32) >> 30 << index_bits) | jnp.arange(n, dtype=jnp.uint32)
    return (jax.lax.sort(packed) & ((1 << index_bits) - 1)).astype(jnp.int32)


def order_uniformity(shuffle, n, watched, draws=2400):
    """The p-value of a chi-square test that the `watched` first indices take every relative
    order in the shuffled output equally often, over `draws` keys."""
    keys = jax.random.split(jax.random.PRNGKey(7), draws)
    shuffled = np.asarray(jax.jit(jax.vmap(shuffle, in_axes=(0, None)), static_argnums=1)(keys, n))
    positions = np.argsort(shuffled, axis=1)[:, :watched]  # where each watched index landed
    seen = collections.Counter(map(tuple, np.argsort(positions, axis=1)))
    return scipy.stats.chisquare([seen[order] for order in itertools.permutations(range(watched))]).pvalue


@pytest.mark.parametrize("n, watched", [(5, 5), (2048, 4), (4097, 4)])  # 1, 2 and 3 rounds of sorting
def test_shuffled_indices_draws_every_order_equally_often(n, watched):
    assert order_uniformity(cpu_workarounds.shuffled_indices, n, watched) > 1e-3


def test_the_uniformity_check_rejects_a_shuffle_with_too_few_random_bits():
    assert order_uniformity(one_round_of_two_random_bits, 2048, 4) < 1e-6


def test_perturb_location_is_uniform_in_plus_minus_alpha_and_key_dependent():
    alpha = 0.5
    loc = jnp.zeros((4096, 3))
    z1 = np.asarray(perturb_location(loc, jax.random.PRNGKey(0), alpha))
    z2 = np.asarray(perturb_location(loc, jax.random.PRNGKey(1), alpha))
    for z in (z1, z2):
        assert z.shape == (4096, 3)
        assert z.min() >= -alpha and z.max() <= alpha
        # U(-a, a): mean 0 (sd of the mean of 12288 draws is ~0.0026), edges reached, sd a/sqrt(3).
        assert abs(z.mean()) < 0.02
        assert z.min() < -0.49 and z.max() > 0.49
        assert abs(z.std() - alpha / np.sqrt(3)) < 0.01
        # Independent per sample and per action dimension.
        assert abs(np.corrcoef(z[:, 0], z[:, 1])[0, 1]) < 0.1
    assert not np.any(z1 == z2)
    assert abs(np.corrcoef(z1.ravel(), z2.ravel())[0, 1]) < 0.1

    # The noise is added to the location, not a replacement for it.
    shifted = np.asarray(perturb_location(loc + 3.0, jax.random.PRNGKey(0), alpha))
    np.testing.assert_allclose(shifted - 3.0, z1, atol=1e-6)


def test_perturb_location_with_zero_alpha_is_the_identity():
    loc = jax.random.normal(jax.random.PRNGKey(2), (64, 3))
    np.testing.assert_array_equal(perturb_location(loc, jax.random.PRNGKey(3), 0.0), loc)


# --------------------------------------------------------------------------------------------
# The loss

OBS_SIZE, ACTION_SIZE, BATCH = 4, 2, 32
# ent_coef > 0 so that the entropy term takes part in the comparison.
LOSS_CONFIG = Config(algo="ppo", ent_coef=0.01)


@pytest.fixture(scope="module")
def loss_setup():
    spec = envs.EnvSpec("loss", OBS_SIZE, ACTION_SIZE, (-1.0,) * ACTION_SIZE, (1.0,) * ACTION_SIZE, 100, "jax")
    actor, critic = make_networks(LOSS_CONFIG, spec)
    k_actor, k_critic, k_obs, k_act, k_lp, k_v, k_adv, k_ret = jax.random.split(jax.random.PRNGKey(4), 8)
    obs = jax.random.normal(k_obs, (BATCH, OBS_SIZE))
    # Scaled-up actor head so that the policy depends on the observation at more than 1e-2 level.
    params = {"actor": actor.init(k_actor, obs[0]), "critic": critic.init(k_critic, obs[0])}
    params["actor"] = jax.tree.map(lambda p: p * 3.0, params["actor"])
    loc, log_scale = actor.apply(params["actor"], obs)
    actions = loc + jax.random.normal(k_act, (BATCH, ACTION_SIZE))
    # Stored log-probs a little away from the current ones, so some ratios are clipped.
    log_probs = policy_distribution(loc, log_scale).log_prob(actions) + 0.3 * jax.random.normal(k_lp, (BATCH,))
    values = critic.apply(params["critic"], obs) + 0.3 * jax.random.normal(k_v, (BATCH,))
    batch = Batch(
        obs, actions, log_probs, values, jax.random.normal(k_adv, (BATCH,)),
        values + jax.random.normal(k_ret, (BATCH,)),
    )  # fmt: skip
    return actor, critic, params, batch


def hand_written_ppo_loss(params, actor, critic, batch, config):
    """CleanRL's clipped PPO loss, with no perturbation anywhere."""
    loc, log_scale = actor.apply(params["actor"], batch.obs)
    dist = policy_distribution(loc, log_scale)
    log_probs = dist.log_prob(batch.actions)
    entropy = dist.entropy().mean()
    ratio = jnp.exp(log_probs - batch.log_probs)
    adv = (batch.advantages - batch.advantages.mean()) / (batch.advantages.std() + 1e-8)
    clip = config.clip_coef
    policy_loss = jnp.maximum(-adv * ratio, -adv * jnp.clip(ratio, 1 - clip, 1 + clip)).mean()
    values = critic.apply(params["critic"], batch.obs)
    unclipped = (values - batch.returns) ** 2
    clipped = (batch.values + jnp.clip(values - batch.values, -clip, clip) - batch.returns) ** 2
    value_loss = 0.5 * jnp.maximum(unclipped, clipped).mean()
    return policy_loss - config.ent_coef * entropy + config.vf_coef * value_loss


def test_rpo_with_zero_alpha_is_bit_identical_to_plain_ppo_loss_and_gradients(loss_setup):
    actor, critic, params, batch = loss_setup
    rpo_zero = dataclasses.replace(LOSS_CONFIG, algo="rpo", rpo_alpha=0.0)
    ppo_config = dataclasses.replace(dataclasses.replace(LOSS_CONFIG, rpo_alpha=0.7), algo="ppo")
    grad_fn = jax.value_and_grad(ppo_loss, has_aux=True)

    (loss_a, metrics_a), grads_a = grad_fn(params, actor, critic, batch, jax.random.PRNGKey(10), rpo_zero)
    # Another config built to be identical, and another key: nothing may change.
    (loss_b, _), grads_b = grad_fn(params, actor, critic, batch, jax.random.PRNGKey(11), ppo_config)
    ref_loss, ref_grads = jax.value_and_grad(hand_written_ppo_loss)(params, actor, critic, batch, rpo_zero)

    assert 0 < float(metrics_a.clip_fraction) < 1  # the clipping branch is really exercised
    for loss, grads in [(loss_b, grads_b), (ref_loss, ref_grads)]:
        assert np.array_equal(loss_a, loss), (float(loss_a), float(loss))
        for ga, gb in zip(jax.tree.leaves(grads_a), jax.tree.leaves(grads), strict=True):
            assert np.array_equal(ga, gb)


def test_rpo_loss_depends_on_perturbation_key_only_when_alpha_positive(loss_setup):
    actor, critic, params, batch = loss_setup
    keys = jax.random.PRNGKey(20), jax.random.PRNGKey(21)
    rpo = dataclasses.replace(LOSS_CONFIG, algo="rpo", rpo_alpha=0.5)
    rpo_losses = [ppo_loss(params, actor, critic, batch, k, rpo)[0] for k in keys]
    ppo_losses = [ppo_loss(params, actor, critic, batch, k, LOSS_CONFIG)[0] for k in keys]
    assert float(rpo_losses[0]) != float(rpo_losses[1])
    assert float(rpo_losses[0]) != float(ppo_losses[0])
    assert np.array_equal(ppo_losses[0], ppo_losses[1])


def test_only_rpo_draws_the_perturbation(loss_setup, monkeypatch):
    # The others train with alpha 0, whose draw would change no number but cost one in every
    # gradient step (test_rpo_with_zero_alpha_is_bit_identical_... shows the numbers agree).
    actor, critic, params, batch = loss_setup
    drawn = []
    monkeypatch.setattr(loss_module, "perturb_location", lambda loc, key, alpha: drawn.append(alpha) or loc)
    for algo in ("ppo", "rad", "drac", "rpo"):
        ppo_loss(params, actor, critic, batch, jax.random.PRNGKey(0), dataclasses.replace(LOSS_CONFIG, algo=algo))
    assert len(drawn) == 1


def test_approx_kl_ignores_the_perturbation(loss_setup):
    # approx_kl must measure the unperturbed policy: with alpha = 2 the perturbed ratio alone
    # would give a KL of order alpha^2 / 6.
    actor, critic, params, batch = loss_setup
    rpo = dataclasses.replace(LOSS_CONFIG, algo="rpo", rpo_alpha=2.0)
    _, rpo_metrics = ppo_loss(params, actor, critic, batch, jax.random.PRNGKey(0), rpo)
    _, ppo_metrics = ppo_loss(params, actor, critic, batch, jax.random.PRNGKey(0), LOSS_CONFIG)
    np.testing.assert_allclose(rpo_metrics.approx_kl, ppo_metrics.approx_kl, rtol=1e-6)
    assert float(rpo_metrics.clip_fraction) > float(ppo_metrics.clip_fraction)


# --------------------------------------------------------------------------------------------
# The perturbation inside a training update

RECORD_ALPHA = 100.0
# 2 epochs x 4 minibatches of 8 samples. A huge alpha makes the perturbation impossible to miss;
# a tiny constant learning rate keeps the policy where the rollout left it.
RECORD_CONFIG = Config(
    total_timesteps=4 * 8, num_envs=4, num_steps=8, num_minibatches=4, update_epochs=2,
    rpo_alpha=RECORD_ALPHA, lr=1e-10, lr_schedule="constant",
)  # fmt: skip


@pytest.fixture(scope="module")
def recorded_update():
    """One jitted update with `perturb_location` wrapped to record, per call at run time, the
    noise it added (through jax.debug.callback) and, at trace time, which function called it."""
    noises, callers = [], []
    original = loss_module.perturb_location

    def recording_perturb_location(loc, key, alpha):
        callers.append(sys._getframe(1).f_code.co_name)
        perturbed = original(loc, key, alpha)
        jax.debug.callback(lambda noise: noises.append(np.array(noise)), perturbed - loc)
        return perturbed

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(loss_module, "perturb_location", recording_perturb_location)
        trainer = make_trainer(RECORD_CONFIG, make_env("cartpole"))
        state = trainer.init(jax.random.PRNGKey(0))
        _, metrics = jax.jit(trainer.update)(state)
        jax.block_until_ready(metrics)
    return noises, callers, metrics


def test_each_minibatch_of_each_epoch_gets_fresh_perturbation(recorded_update):
    noises, _, _ = recorded_update
    config = RECORD_CONFIG
    assert len(noises) == config.update_epochs * config.num_minibatches
    for noise in noises:
        assert noise.shape == (config.minibatch_size, 1)
        # perturbed - loc in float32: allow the rounding of values near 100.
        assert np.all(np.abs(noise) <= RECORD_ALPHA * (1 + 1e-6))
    assert max(np.abs(n).max() for n in noises) > RECORD_ALPHA / 2
    # Reusing one key across minibatches or epochs would repeat a noise vector exactly.
    sums = [float(n.sum()) for n in noises]
    assert len(set(sums)) == len(sums), sums


def test_rollout_log_probs_are_unperturbed(recorded_update):
    _, callers, metrics = recorded_update
    # The perturbation is only ever traced from inside the loss, never from the rollout.
    assert callers and set(callers) == {"trained_policy"}  # the loss's, in loss.py
    # With the policy held still (lr 1e-10), approx_kl compares the unperturbed policy with the
    # stored rollout log-probs. Had the rollout stored log-probs of a location perturbed by
    # U(-100, 100), it would be of order 100^2; stored correctly, it is rounding noise.
    assert float(metrics.approx_kl) < 1e-6
    # Meanwhile the loss itself did see the huge perturbation: nearly every ratio is clipped.
    assert float(metrics.clip_fraction) > 0.5


# --------------------------------------------------------------------------------------------
# Config validation


@pytest.mark.parametrize(
    "overrides, field",
    [
        (dict(total_timesteps=0), "total_timesteps"),
        (dict(total_timesteps=-5), "total_timesteps"),
        (dict(num_envs=0), "num_envs"),
        (dict(num_envs=-1), "num_envs"),
        (dict(num_steps=0), "num_steps"),
        (dict(num_minibatches=0), "num_minibatches"),
        (dict(update_epochs=0), "update_epochs"),
        (dict(num_minibatches=3), "num_minibatches"),  # 64 * 32 = 2048 is not divisible by 3
        (dict(num_envs=1, num_steps=4, num_minibatches=4), "num_minibatches"),  # 1 sample each
        (dict(clip_coef=0.0), "clip_coef"),
        (dict(clip_coef=-0.2), "clip_coef"),
        (dict(rpo_alpha=-0.1), "rpo_alpha"),
        (dict(gamma=0.0), "gamma"),
        (dict(gamma=1.5), "gamma"),
        (dict(gamma=-0.1), "gamma"),
        (dict(gae_lambda=0.0), "gae_lambda"),
        (dict(gae_lambda=1.5), "gae_lambda"),
        (dict(gae_lambda=-0.1), "gae_lambda"),
        (dict(total_timesteps=2047), "total_timesteps"),  # below one batch of 64 * 32
    ],
)
def test_invalid_config_raises_value_error_naming_the_field(overrides, field):
    with pytest.raises(ValueError, match=rf"^{field}\b"):
        Config(**overrides).validate()


@pytest.mark.parametrize(
    "overrides",
    [
        dict(),
        dict(gamma=1.0, gae_lambda=1.0),  # the closed end of (0, 1]
        dict(rpo_alpha=0.0),
        dict(num_envs=1, num_steps=4, num_minibatches=2),  # minibatches of exactly 2
        dict(total_timesteps=64 * 32),  # exactly one batch
    ],
)
def test_boundary_configs_are_valid(overrides):
    config = Config(**overrides)
    assert config.validate() is config


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_presets_validate(name):
    assert PRESETS[name].validate() is PRESETS[name]
