"""PPO and RPO as one jittable training function.

    train = make_train(config, env)          # env: a single environment, see rpo_jax.envs
    state, metrics = jax.jit(train)(key)     # metrics: one scalar per update per field
    jax.jit(jax.vmap(train))(keys)           # several seeds in one program

RPO differs from PPO in one line of `ppo_loss`: during the update the policy's location is
perturbed by U(-rpo_alpha, rpo_alpha) noise (`networks.perturb_location`). Rollouts sample from
the unperturbed policy and store that log-probability. `rpo_alpha = 0` is exactly PPO.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable

import jax
import jax.numpy as jnp
import optax
from flax import struct

from rpo_jax import envs
from rpo_jax.networks import ACTIVATIONS, DISTRIBUTIONS, Actor, Critic, perturb_location, policy_distribution


@dataclasses.dataclass(frozen=True)
class Config:
    """Hyperparameters of one training run. The defaults are a CPU-sized Cartpole run."""

    total_timesteps: int = 1_000_000
    """environment steps per run over all parallel environments (rounded down to whole batches)"""
    num_envs: int = 64
    """parallel environments in the rollout"""
    num_steps: int = 32
    """rollout length per environment and update"""
    num_minibatches: int = 4
    """minibatches per epoch; the batch is num_envs * num_steps samples"""
    update_epochs: int = 4
    """passes over the batch per update"""
    lr: float = 1e-3
    """Adam learning rate (the start value for the linear and adaptive schedules)"""
    lr_schedule: str = "linear"
    """'linear' (annealed to 0), 'constant', or 'adaptive' (rl_games: x/÷1.5 to keep KL near kl_target)"""
    kl_target: float = 0.008
    """target approx-KL per minibatch for the adaptive schedule"""
    gamma: float = 0.99
    """discount factor"""
    gae_lambda: float = 0.95
    """GAE lambda"""
    clip_coef: float = 0.2
    """PPO ratio clip, also used to clip the value loss"""
    clip_value_loss: bool = True
    """clip the value update around the rollout's value estimate"""
    vf_coef: float = 0.5
    """value-loss coefficient"""
    ent_coef: float = 0.0
    """entropy-bonus coefficient"""
    max_grad_norm: float = 0.5
    """global-norm gradient clip"""
    adam_eps: float = 1e-5
    """Adam epsilon"""
    norm_adv: bool = True
    """normalise advantages per minibatch"""
    rpo_alpha: float = 0.0
    """RPO: half-width of the uniform perturbation of the policy location; 0 is PPO"""
    dist: str = "gaussian"
    """action distribution: gaussian, laplace or gumbel (state-dependent location, free log-scale)"""
    augmentation: str = "none"
    """'none', 'rad' (train on amplitude-scaled observations) or 'drac' (regularise towards them)"""
    aug_low: float = 0.6
    """lower bound of the amplitude-scaling factor of RAD and DrAC"""
    aug_high: float = 1.2
    """upper bound of the amplitude-scaling factor of RAD and DrAC"""
    drac_coef: float = 0.1
    """weight of DrAC's policy-KL and value regularisers"""
    hidden_sizes: tuple[int, ...] = (64, 64)
    """hidden layer sizes of both the actor and the critic"""
    activation: str = "tanh"
    """hidden activation: tanh, relu, elu or silu"""
    normalize_obs: bool = True
    """normalise observations by running statistics"""
    obs_clip: float = 10.0
    """clip of normalised observations"""
    normalize_reward: bool = True
    """divide rewards by the running std of the discounted return"""
    reward_clip: float = 10.0
    """clip of normalised rewards"""
    reward_scale: float = 1.0
    """constant factor applied to rewards before normalisation"""
    normalize_value: bool = False
    """the critic predicts returns standardised by their running mean and std (rl_games' value normalisation)"""

    @property
    def batch_size(self) -> int:
        return self.num_envs * self.num_steps

    @property
    def minibatch_size(self) -> int:
        return self.batch_size // self.num_minibatches

    @property
    def num_updates(self) -> int:
        return self.total_timesteps // self.batch_size

    def validate(self) -> "Config":
        """Raises ValueError naming the first invalid field and what is allowed."""
        for name in ("total_timesteps", "num_envs", "num_steps", "num_minibatches", "update_epochs"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be a positive integer, got {getattr(self, name)}")
        for name in ("lr", "clip_coef", "max_grad_norm", "adam_eps", "obs_clip", "reward_clip", "kl_target"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("gamma", "gae_lambda"):
            if not 0 < getattr(self, name) <= 1:
                raise ValueError(f"{name} must be in (0, 1], got {getattr(self, name)}")
        for name in ("rpo_alpha", "ent_coef", "vf_coef", "drac_coef"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if not self.reward_scale > 0:
            raise ValueError(f"reward_scale must be > 0, got {self.reward_scale}")
        if self.batch_size % self.num_minibatches:
            raise ValueError(
                f"num_minibatches must divide num_envs * num_steps = {self.batch_size}, "
                f"got {self.num_minibatches}"
            )
        if self.minibatch_size < 2:
            raise ValueError(
                f"num_minibatches must leave at least 2 samples per minibatch, got "
                f"{self.num_minibatches} minibatches of a batch of {self.batch_size}"
            )
        if self.total_timesteps < self.batch_size:
            raise ValueError(
                f"total_timesteps must be at least one batch (num_envs * num_steps = "
                f"{self.batch_size}), got {self.total_timesteps}"
            )
        if not self.hidden_sizes or min(self.hidden_sizes) <= 0:
            raise ValueError(f"hidden_sizes must be positive integers, got {self.hidden_sizes}")
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"activation must be one of {', '.join(ACTIVATIONS)}, got {self.activation!r}")
        if self.lr_schedule not in LR_SCHEDULES:
            raise ValueError(f"lr_schedule must be one of {', '.join(LR_SCHEDULES)}, got {self.lr_schedule!r}")
        if self.dist not in DISTRIBUTIONS:
            raise ValueError(f"dist must be one of {', '.join(DISTRIBUTIONS)}, got {self.dist!r}")
        if self.augmentation not in AUGMENTATIONS:
            raise ValueError(f"augmentation must be one of {', '.join(AUGMENTATIONS)}, got {self.augmentation!r}")
        if not 0 < self.aug_low <= self.aug_high:
            raise ValueError(
                f"aug_low and aug_high must satisfy 0 < aug_low <= aug_high, got {self.aug_low}, {self.aug_high}"
            )
        return self


LR_SCHEDULES = ("linear", "constant", "adaptive")
AUGMENTATIONS = ("none", "rad", "drac")


@struct.dataclass
class Hyperparams:
    """The continuous hyperparameters a sweep may vary. They live in the training state as
    arrays, so `jax.vmap` over a batch of them (and of keys) trains a whole grid in one
    program. Each leaf is [] for one run, [R] for a batch of runs."""

    rpo_alpha: jax.Array
    ent_coef: jax.Array
    lr: jax.Array
    drac_coef: jax.Array

    @classmethod
    def from_config(cls, config: "Config") -> "Hyperparams":
        return cls(*(jnp.asarray(getattr(config, name), jnp.float32) for name in SWEEPABLE))


SWEEPABLE = tuple(Hyperparams.__dataclass_fields__)

PRESETS: dict[str, Config] = {
    # CleanRL's ppo_continuous_action / rpo_continuous_action, as in the paper.
    "paper": Config(
        total_timesteps=8_000_000, num_envs=1, num_steps=2048, num_minibatches=32,
        update_epochs=10, lr=3e-4, lr_schedule="linear", vf_coef=0.5, max_grad_norm=0.5,
    ),
    # rl_games' IsaacGym Cartpole config. Kept: sizes, ELU [32, 32], KL-adaptive lr, value
    # coefficient 4 (rl_games halves its squared error too), grad norm 1, reward scale 0.1,
    # observation normalisation with the task's +-5 clip. rl_games' value normalisation is
    # `normalize_value`, left off here so that the Cartpole results stay comparable; its shared
    # actor-critic trunk is not reproduced (rpo_jax keeps them separate).
    "isaacgym": Config(
        total_timesteps=819_200, num_envs=512, num_steps=16, num_minibatches=1,
        update_epochs=8, lr=3e-4, lr_schedule="adaptive", kl_target=0.008, vf_coef=4.0,
        max_grad_norm=1.0, hidden_sizes=(32, 32), activation="elu", normalize_reward=False,
        reward_scale=0.1, obs_clip=5.0,
    ),
}  # fmt: skip
# rl_games' IsaacGym BallBalance config: Cartpole's with an MLP [128, 64, 32], 4096 environments
# in minibatches of 8192 and value normalisation (without it BallBalance plateaus near 245, see
# benchmarks/RESULTS.md), for its 250 updates (16M steps).
PRESETS["isaacgym-ballbalance"] = dataclasses.replace(
    PRESETS["isaacgym"], total_timesteps=16_384_000, num_envs=4096, num_minibatches=8,
    hidden_sizes=(128, 64, 32), normalize_value=True,
)  # fmt: skip


# --------------------------------------------------------------------------------------------
# The maths


def compute_gae(
    rewards: jax.Array,
    values: jax.Array,
    next_values: jax.Array,
    terminated: jax.Array,
    truncated: jax.Array,
    gamma: float,
    gae_lambda: float,
) -> tuple[jax.Array, jax.Array]:
    """Generalised advantage estimation with termination and truncation kept apart.

    All inputs are [T, N]. `next_values[t]` is the value of the observation step t reached,
    before any auto-reset (the final observation when the episode ended there). A terminated
    step does not bootstrap; a truncated step bootstraps from its final observation's value;
    either ends the advantage recursion. Returns (advantages, returns), both [T, N].
    """
    not_terminated = 1.0 - terminated.astype(values.dtype)
    continues = 1.0 - (terminated | truncated).astype(values.dtype)
    deltas = rewards + gamma * next_values * not_terminated - values

    def backward(advantage, step):
        delta, cont = step
        advantage = delta + gamma * gae_lambda * cont * advantage
        return advantage, advantage

    _, advantages = jax.lax.scan(backward, jnp.zeros_like(values[0]), (deltas, continues), reverse=True)
    return advantages, advantages + values


@struct.dataclass
class Batch:
    """Rollout samples flattened over time and environments; leading axis [B]."""

    obs: jax.Array  # [B, obs_size]
    actions: jax.Array  # [B, action_size] as sampled, before clipping to the bounds
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


def ppo_loss(
    params: dict,
    actor: Actor,
    critic: Critic,
    batch: Batch,
    key: jax.Array,
    config: Config,
    hparams: Hyperparams | None = None,
) -> tuple[jax.Array, LossMetrics]:
    """Clipped-surrogate PPO loss on one minibatch [B]; with rpo_alpha > 0, the RPO loss.

    The policy location is perturbed (RPO) before the log-probability and entropy of the
    stored actions are taken. With `augmentation='rad'` the policy and value see amplitude-
    scaled observations; with 'drac' they see the originals and DrAC's regularisers pull the
    outputs on scaled observations towards them. `approx_kl` measures how far the unperturbed
    policy moved from the rollout policy: the perturbation alone would add about
    alpha^2 / (6 sigma^2) to it and starve the adaptive learning-rate schedule.
    `hparams` defaults to the config's values. Returns the scalar loss and its parts."""
    hparams = Hyperparams.from_config(config) if hparams is None else hparams
    perturb_key, augment_key = jax.random.split(key)
    obs = batch.obs
    if config.augmentation == "rad":
        obs = amplitude_scale(obs, augment_key, config.aug_low, config.aug_high)
    loc, log_scale = actor.apply(params["actor"], obs)
    dist = policy_distribution(perturb_location(loc, perturb_key, hparams.rpo_alpha), log_scale, config.dist)
    log_probs = dist.log_prob(batch.actions)
    entropy = dist.entropy().mean()

    ratio = jnp.exp(log_probs - batch.log_probs)
    unperturbed_log_ratio = jax.lax.stop_gradient(
        policy_distribution(loc, log_scale, config.dist).log_prob(batch.actions) - batch.log_probs
    )
    advantages = batch.advantages
    if config.norm_adv:
        advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
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
        aug_loc, aug_log_scale = actor.apply(params["actor"], augmented)
        # DrAC holds the outputs on the original observation fixed and moves those on the
        # augmented one towards them.
        target = policy_distribution(*jax.lax.stop_gradient((loc, log_scale)), config.dist)
        policy_regulariser = target.kl_divergence(policy_distribution(aug_loc, aug_log_scale, config.dist)).mean()
        value_regulariser = ((jax.lax.stop_gradient(values) - critic.apply(params["critic"], augmented)) ** 2).mean()
        loss = loss + hparams.drac_coef * (policy_regulariser + value_regulariser)
    metrics = LossMetrics(
        policy_loss=policy_loss,
        value_loss=value_loss,
        policy_entropy=entropy,
        approx_kl=(jnp.expm1(unperturbed_log_ratio) - unperturbed_log_ratio).mean(),
        clip_fraction=(jnp.abs(ratio - 1) > config.clip_coef).mean(),
    )
    return loss, metrics


# --------------------------------------------------------------------------------------------
# Training


@struct.dataclass
class TrainState:
    params: dict  # {"actor": ..., "critic": ...}
    opt_state: Any
    env_state: Any
    obs: jax.Array  # [N, obs_size] normalised observation to act on
    key: jax.Array
    update: jax.Array  # [] updates done
    hparams: Hyperparams
    value_stats: envs.RunningMeanStd  # [] statistics of the returns; unused without normalize_value
    last_episode_return: jax.Array  # [] carried forward through updates that finish no episode
    last_episode_length: jax.Array


@struct.dataclass
class Metrics:
    """Per-update scalars (a leading [updates] axis after a scan, [seeds] under vmap)."""

    env_steps: jax.Array
    episode_return: jax.Array  # mean over episodes finished in this update, else carried forward
    episode_length: jax.Array
    episodes_finished: jax.Array
    policy_entropy: jax.Array
    policy_loss: jax.Array
    value_loss: jax.Array
    approx_kl: jax.Array
    clip_fraction: jax.Array
    action_std: jax.Array
    learning_rate: jax.Array


@struct.dataclass
class Transition:
    obs: jax.Array
    final_obs: jax.Array
    action: jax.Array
    log_prob: jax.Array
    reward: jax.Array
    terminated: jax.Array
    truncated: jax.Array
    episode_return: jax.Array
    episode_length: jax.Array


def wrap_for_training(env: envs.Env, config: Config) -> envs.Env:
    """The batched environment the trainer steps: `env` itself if it is already batched (an
    `envs.BatchedEnv`), else `config.num_envs` vmapped copies. The observation normaliser is
    outermost so that its statistics sit at `env_state.obs_stats`, where saved policies read them."""
    if not isinstance(env, envs.BatchedEnv):
        env = envs.vectorize(env, config.num_envs)
    elif env.num_envs != config.num_envs:
        raise ValueError(f"num_envs must match the vector environment's {env.num_envs}, got {config.num_envs}")
    vec = envs.EpisodeStatistics(env)
    vec = envs.ClipAction(vec)
    vec = envs.NormalizeReward(vec, config.gamma, config.reward_clip, config.reward_scale, config.normalize_reward)
    return envs.NormalizeObservation(vec, config.obs_clip, enabled=config.normalize_obs)


def make_optimizer(config: Config) -> optax.GradientTransformation:
    """Global-norm clipping then Adam, with the learning rate held in the state so that the
    linear and adaptive schedules set it between steps."""

    def chain(learning_rate):
        return optax.chain(
            optax.clip_by_global_norm(config.max_grad_norm),
            optax.adam(learning_rate, eps=config.adam_eps),
        )

    return optax.inject_hyperparams(chain)(learning_rate=config.lr)


def set_learning_rate(opt_state: Any, lr: jax.Array) -> Any:
    return opt_state._replace(hyperparams={**opt_state.hyperparams, "learning_rate": lr})


def make_networks(config: Config, action_size: int) -> tuple[Actor, Critic]:
    actor = Actor(action_size, tuple(config.hidden_sizes), config.activation)
    return actor, Critic(tuple(config.hidden_sizes), config.activation)


@dataclasses.dataclass(frozen=True)
class Trainer:
    """`init(key)` builds the state; `run(state, n)` does n updates in one `lax.scan`.

    Both are pure and jittable. A long run calls one compiled `run` chunk repeatedly (all
    chunks the same length, so it compiles once) to report progress between chunks.
    `restart_episodes(state)` replaces the episodes in flight by fresh ones and keeps the rest
    (see there)."""

    config: Config
    init: Callable[..., TrainState]
    update: Callable[[TrainState], tuple[TrainState, Metrics]]
    restart_episodes: Callable[[TrainState], TrainState]

    def run(self, state: TrainState, num_updates: int) -> tuple[TrainState, Metrics]:
        return jax.lax.scan(lambda s, _: self.update(s), state, None, length=num_updates)


def make_trainer(config: Config, env: envs.Env) -> Trainer:
    config.validate()
    spec = env.spec
    train_env = wrap_for_training(env, config)
    actor, critic = make_networks(config, spec.action_size)
    optimizer = make_optimizer(config)
    num_updates = config.num_updates

    def init(key: jax.Array, hparams: Hyperparams | None = None) -> TrainState:
        hparams = Hyperparams.from_config(config) if hparams is None else hparams
        key, actor_key, critic_key, env_key = jax.random.split(key, 4)
        dummy_obs = jnp.zeros((spec.observation_size,))
        params = {"actor": actor.init(actor_key, dummy_obs), "critic": critic.init(critic_key, dummy_obs)}
        env_state, ts = train_env.reset(env_key)
        zero = jnp.zeros(())
        opt_state = set_learning_rate(optimizer.init(params), hparams.lr)
        return TrainState(
            params, opt_state, env_state, ts.obs, key, jnp.zeros((), jnp.int32), hparams,
            envs.RunningMeanStd.zeros(()), zero, zero,
        )  # fmt: skip

    def rollout_step(params, carry, key):
        env_state, obs = carry
        loc, log_scale = actor.apply(params["actor"], obs)
        action, log_prob = policy_distribution(loc, log_scale, config.dist).sample_and_log_prob(seed=key)
        env_state, ts = train_env.step(env_state, action)
        transition = Transition(
            obs, ts.final_obs, action, log_prob, ts.reward, ts.terminated, ts.truncated,
            ts.info["episode_return"], ts.info["episode_length"],
        )  # fmt: skip
        return (env_state, ts.obs), transition

    def minibatch_step(hparams, carry, inputs):
        params, opt_state = carry
        batch, loss_key = inputs
        grads, metrics = jax.grad(ppo_loss, has_aux=True)(params, actor, critic, batch, loss_key, config, hparams)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        params = optax.apply_updates(params, updates)
        if config.lr_schedule == "adaptive":
            lr = opt_state.hyperparams["learning_rate"]
            lr = jnp.where(metrics.approx_kl > 2 * config.kl_target, jnp.maximum(lr / 1.5, 1e-6), lr)
            lr = jnp.where(metrics.approx_kl < 0.5 * config.kl_target, jnp.minimum(lr * 1.5, 1e-2), lr)
            opt_state = set_learning_rate(opt_state, lr)
        return (params, opt_state), metrics

    def epoch(hparams, carry, key):
        batch, params, opt_state = carry
        permute_key, loss_key = jax.random.split(key)
        permutation = jax.random.permutation(permute_key, config.batch_size)
        minibatches = jax.tree.map(
            lambda x: x[permutation].reshape(config.num_minibatches, config.minibatch_size, *x.shape[1:]),
            batch,
        )
        loss_keys = jax.random.split(loss_key, config.num_minibatches)
        (params, opt_state), metrics = jax.lax.scan(
            functools.partial(minibatch_step, hparams), (params, opt_state), (minibatches, loss_keys)
        )
        return (batch, params, opt_state), metrics

    def update(state: TrainState) -> tuple[TrainState, Metrics]:
        key, rollout_key, epochs_key = jax.random.split(state.key, 3)
        opt_state = state.opt_state
        if config.lr_schedule == "linear":
            opt_state = set_learning_rate(opt_state, state.hparams.lr * (1.0 - state.update / num_updates))
        learning_rate = opt_state.hyperparams["learning_rate"]

        params = state.params
        (env_state, obs), traj = jax.lax.scan(
            functools.partial(rollout_step, params),
            (state.env_state, state.obs),
            jax.random.split(rollout_key, config.num_steps),
        )
        # Values in two large batched calls after the rollout rather than one per step.
        values = critic.apply(params["critic"], traj.obs)
        next_values = critic.apply(params["critic"], traj.final_obs)
        value_stats = state.value_stats
        if config.normalize_value:
            values, next_values = value_stats.unstandardize(values), value_stats.unstandardize(next_values)
        advantages, returns = compute_gae(
            traj.reward, values, next_values, traj.terminated, traj.truncated, config.gamma, config.gae_lambda
        )
        if config.normalize_value:
            # The critic learns the new returns on the scale of statistics that include them.
            value_stats = value_stats.update(returns.reshape(-1))
            values, returns = value_stats.standardize(values), value_stats.standardize(returns)
        batch = jax.tree.map(
            lambda x: x.reshape(config.batch_size, *x.shape[2:]),
            Batch(traj.obs, traj.action, traj.log_prob, values, advantages, returns),
        )
        (_, params, opt_state), loss_metrics = jax.lax.scan(
            functools.partial(epoch, state.hparams),
            (batch, params, opt_state),
            jax.random.split(epochs_key, config.update_epochs),
        )

        done = traj.terminated | traj.truncated
        finished = done.sum()
        any_finished = finished > 0
        episode_return = jnp.where(any_finished, traj.episode_return.sum() / jnp.maximum(finished, 1), state.last_episode_return)
        episode_length = jnp.where(
            any_finished, traj.episode_length.sum() / jnp.maximum(finished, 1), state.last_episode_length
        )
        update_count = state.update + 1
        metrics = Metrics(
            env_steps=update_count * config.batch_size,
            episode_return=episode_return,
            episode_length=episode_length,
            episodes_finished=finished,
            action_std=jnp.exp(params["actor"]["params"]["log_std"]).mean(),
            learning_rate=learning_rate,
            **{name: getattr(loss_metrics, name).mean() for name in LossMetrics.__dataclass_fields__},
        )
        new_state = TrainState(
            params, opt_state, env_state, obs, key, update_count, state.hparams, value_stats,
            episode_return, episode_length,
        )  # fmt: skip
        return new_state, metrics

    def restart_episodes(state: TrainState) -> TrainState:
        """`state` with a fresh episode in every environment; parameters, optimiser, counters
        and the normalisers' statistics stay. A resumed run needs this for host-side simulators,
        whose state lives outside JAX and so in no checkpoint."""
        key, reset_key = jax.random.split(state.key)
        env_state, ts = train_env.restart(state.env_state, reset_key)
        return state.replace(env_state=env_state, obs=ts.obs, key=key)

    return Trainer(config, init, update, restart_episodes)


def make_train(config: Config, env: envs.Env) -> Callable[..., tuple[TrainState, Metrics]]:
    """`train(key, hparams=None) -> (final state, per-update metrics)`: the whole run,
    jittable and vmappable. `jax.vmap(train)(keys, hparams)` with [R]-leaved `Hyperparams`
    trains a sweep of R runs (grid points x seeds) in one program."""
    trainer = make_trainer(config, env)

    def train(key: jax.Array, hparams: Hyperparams | None = None) -> tuple[TrainState, Metrics]:
        return trainer.run(trainer.init(key, hparams), config.num_updates)

    return train
