"""The PPO and RPO loss on one minibatch, and the estimates it is built from: generalised
advantage estimation (`compute_gae`), RAD's amplitude scaling and DrAC's regularisers. Pure
functions of arrays; `rpo_jax.ppo` builds the training loop around them.

RPO differs from PPO in one line of `ppo_loss`: during the update the policy's location is
perturbed by U(-rpo_alpha, rpo_alpha) noise (`networks.perturb_location`). Rollouts sample from
the unperturbed policy and store that log-probability. `rpo_alpha = 0` is exactly PPO. The
sweepable hyperparameters (`Hyperparams`) are read here.
"""

from __future__ import annotations

import distrax
import jax
import jax.numpy as jnp
from flax import struct

from rpo_jax.config import Config
from rpo_jax.hyperparams import Hyperparams
from rpo_jax.networks import Actor, Critic, TanhNormal, perturb_location, policy_distribution, policy_entropy

# Steps of the GAE recursion per iteration of its loop. More let XLA fuse steps; on the CPU that
# is no faster and rounds otherwise; untried on a GPU.
GAE_UNROLL = 1


def compute_gae(
    rewards: jax.Array,
    values: jax.Array,
    next_values: jax.Array,
    terminated: jax.Array,
    truncated: jax.Array,
    gamma: float,
    gae_lambda: float,
    truncation: str = "bootstrap",
) -> tuple[jax.Array, jax.Array]:
    """Generalised advantage estimation with termination and truncation kept apart.

    All inputs are [T, N]. `next_values[t]` is the value of the observation step t reached,
    before any auto-reset (the final observation when the episode ended there). A terminated
    step does not bootstrap; a truncated step bootstraps from its final observation's value
    (`truncation="bootstrap"`) or, with "terminate", is treated as terminated, which is what
    the paper's code (CleanRL) does with every episode end. Either ends the advantage
    recursion. Returns (advantages, returns), both [T, N].
    """
    if truncation == "terminate":
        terminated = terminated | truncated
    not_terminated = 1.0 - terminated.astype(values.dtype)
    continues = 1.0 - (terminated | truncated).astype(values.dtype)
    deltas = rewards + gamma * next_values * not_terminated - values

    def backward(advantage, step):
        delta, cont = step
        advantage = delta + gamma * gae_lambda * cont * advantage
        return advantage, advantage

    _, advantages = jax.lax.scan(backward, jnp.zeros_like(values[0]), (deltas, continues), reverse=True, unroll=GAE_UNROLL)
    return advantages, advantages + values


@struct.dataclass
class Batch:
    """Rollout samples flattened over time and environments; leading axis [B]."""

    obs: jax.Array  # [B, obs_size]
    actions: jax.Array  # [B, action_size] as sampled (tanh-normal's u, before the squash), before clipping to the bounds
    log_probs: jax.Array  # [B] under the unperturbed rollout policy
    values: jax.Array  # [B]
    advantages: jax.Array  # [B]
    returns: jax.Array  # [B]


@struct.dataclass
class LossMetrics:
    policy_loss: jax.Array
    value_loss: jax.Array
    policy_entropy: jax.Array
    approx_kl: jax.Array
    clip_fraction: jax.Array


def amplitude_scale(obs: jax.Array, key: jax.Array, low: float, high: float) -> jax.Array:
    """RAD's random amplitude scaling s' = s * u, u ~ U(low, high). obs: [B, obs_size].

    u is drawn per sample and per observation dimension. A single factor per sample would
    keep every ratio between state features, and the features of a proprioceptive state
    (positions, velocities, forces) have unrelated units, so scaling them independently is
    the perturbation of the state's amplitudes that the augmentation is meant to be robust to."""
    return obs * jax.random.uniform(key, obs.shape, obs.dtype, minval=low, maxval=high)


def drac_regulariser(
    params: dict, actor: Actor, critic: Critic, augmented: jax.Array, loc: jax.Array, log_scale: jax.Array,
    values: jax.Array, dist: str,
) -> jax.Array:  # fmt: skip
    """DrAC's KL(pi(.|s) || pi(.|f(s))) + (V(s) - V(f(s)))^2 on augmented observations f(s) [B, obs].

    The outputs on the original observation (loc, log_scale, values) are held fixed, and those
    on the augmented one move towards them."""
    aug_loc, aug_log_scale = actor.apply(params["actor"], augmented)
    target = policy_distribution(*jax.lax.stop_gradient((loc, log_scale)), dist)
    policy_regulariser = target.kl_divergence(policy_distribution(aug_loc, aug_log_scale, dist)).mean()
    value_regulariser = ((jax.lax.stop_gradient(values) - critic.apply(params["critic"], augmented)) ** 2).mean()
    return policy_regulariser + value_regulariser


def trained_policy(
    loc: jax.Array, log_scale: jax.Array, actions: jax.Array, key: jax.Array, config: Config, hparams: Hyperparams
) -> tuple[distrax.Distribution | TanhNormal, jax.Array, jax.Array]:
    """The policy the loss trains on a minibatch [B] (RPO's with its location perturbed), the
    stored actions' log-probabilities [B] under it, and under the unperturbed policy. Only RPO
    perturbs: the others' alpha is 0, whose draw would change no number (loc + 0 is loc) but cost
    a random draw and a second log-probability in every gradient step."""
    policy = policy_distribution(loc, log_scale, config.dist)
    if not config.algorithm.perturbs_location:
        log_probs = policy.log_prob(actions)
        return policy, log_probs, log_probs
    perturbed = policy_distribution(perturb_location(loc, key, hparams.rpo_alpha), log_scale, config.dist)
    return perturbed, perturbed.log_prob(actions), policy.log_prob(actions)


def ppo_loss(
    params: dict,
    actor: Actor,
    critic: Critic,
    batch: Batch,
    key: jax.Array,
    config: Config,
    hparams: Hyperparams | None = None,
    axis_name: str | None = None,
) -> tuple[jax.Array, LossMetrics]:
    """Clipped-surrogate PPO loss on one minibatch [B]; for an algorithm that perturbs the policy's
    location (`Algorithm.perturbs_location`: rpo), the RPO loss at `hparams.rpo_alpha`.

    The policy location is perturbed (RPO) before the log-probability and entropy of the
    stored actions are taken. With `augmentation='rad'` the policy and value see amplitude-
    scaled observations; with 'drac' they see the originals and DrAC's regularisers pull the
    outputs on scaled observations towards them. `approx_kl` measures how far the unperturbed
    policy moved from the rollout policy: the perturbation alone would add about
    alpha^2 / (6 sigma^2) to it and starve the adaptive learning-rate schedule.
    `hparams` defaults to the config's values. With `axis_name`, `batch` is this device's share
    of a minibatch split over that axis. Returns the scalar loss and its parts."""
    hparams = Hyperparams.from_config(config) if hparams is None else hparams
    perturb_key, augment_key = jax.random.split(key)
    obs = batch.obs
    if config.augmentation == "rad":
        obs = amplitude_scale(obs, augment_key, config.aug_low, config.aug_high)
    loc, log_scale = actor.apply(params["actor"], obs)
    dist, log_probs, unperturbed_log_probs = trained_policy(loc, log_scale, batch.actions, perturb_key, config, hparams)
    # A key of its own for tanh-normal's sampled entropy estimate; the other families ignore it.
    entropy = policy_entropy(dist, jax.random.fold_in(key, 2)).mean()

    ratio = jnp.exp(log_probs - batch.log_probs)
    unperturbed_log_ratio = jax.lax.stop_gradient(unperturbed_log_probs - batch.log_probs)
    advantages = batch.advantages
    if config.norm_adv:
        advantages = normalize_advantages(advantages, axis_name)
    policy_loss = jnp.maximum(
        -advantages * ratio, -advantages * jnp.clip(ratio, 1 - config.clip_coef, 1 + config.clip_coef)
    ).mean()

    values = critic.apply(params["critic"], obs)
    value_error = (values - batch.returns) ** 2
    if config.clip_value_loss:
        clipped = batch.values + jnp.clip(values - batch.values, -config.clip_coef, config.clip_coef)
        value_error = jnp.maximum(value_error, (clipped - batch.returns) ** 2)
    value_loss = 0.5 * value_error.mean()

    loss = policy_loss - hparams.ent_coef * entropy + config.vf_coef * value_loss
    if config.augmentation == "drac":
        augmented = amplitude_scale(obs, augment_key, config.aug_low, config.aug_high)
        loss = loss + hparams.drac_coef * drac_regulariser(params, actor, critic, augmented, loc, log_scale, values, config.dist)
    metrics = LossMetrics(
        policy_loss=policy_loss,
        value_loss=value_loss,
        policy_entropy=entropy,
        approx_kl=(jnp.expm1(unperturbed_log_ratio) - unperturbed_log_ratio).mean(),
        clip_fraction=(jnp.abs(ratio - 1) > config.clip_coef).mean(),
    )
    return loss, metrics


def normalize_advantages(advantages: jax.Array, axis_name: str | None = None) -> jax.Array:
    """Advantages of a minibatch [B] standardised by its mean and std; with `axis_name`, by those
    of the whole minibatch, whose equal shares lie on the devices of that axis."""
    if axis_name is None:
        return (advantages - advantages.mean()) / (advantages.std() + 1e-8)
    mean = jax.lax.pmean(advantages.mean(), axis_name)
    std = jnp.sqrt(jax.lax.pmean(((advantages - mean) ** 2).mean(), axis_name))
    return (advantages - mean) / (std + 1e-8)
