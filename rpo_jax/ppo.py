"""PPO and RPO as one jittable training function, read top to bottom as the paper's Algorithm 1.

    train = make_train(config, env)          # env: a single environment, see rpo_jax.envs
    state, metrics = jax.jit(train)(key)     # metrics: one scalar per update per field
    jax.jit(jax.vmap(train))(keys)           # several seeds in one program

The state (`TrainState`), the trainer (`Trainer`: the static parts and the entry points), then
one update: `collect` (`rollout` the environments under the current policy, `make_batch` its
values, advantages and batch) and `learn` (`minibatch_epochs` of `gradient_step`s, the one
place where gradients are taken and the optimiser steps). The loss and the advantages are
`rpo_jax.loss`'s, where RPO differs from PPO.

A trainer made with `axis_name` (and `env_shards` D) is one device's part of a run whose
environments are split over that device axis (data parallel, see `rpo_jax.parallel.devices`):
it steps num_envs / D environments, `gradient_step` averages the gradients and loss metrics
over the axis, the normalisers merge their statistics over it, advantages are normalised by the
statistics of the whole minibatch, and the random draws that differ per environment or per
sample (actions, resets, minibatch shuffles, RPO's noise) come from keys folded with the
device's index, so no two devices draw alike.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable

import jax
import jax.numpy as jnp
import optax
from flax import struct

from rpo_jax import diagnostics, envs, optimizer
from rpo_jax.acting import make_actor, wrap_for_training
from rpo_jax.config import Config
from rpo_jax.cpu_workarounds import shuffled_indices
from rpo_jax.hyperparams import Hyperparams
from rpo_jax.loss import Batch, LossMetrics, compute_gae, ppo_loss
from rpo_jax.networks import Actor, Critic, mean_scale, policy_distribution, to_action

# ---------------------------------------------------------------- the state


@struct.dataclass
class TrainState:
    params: dict  # {"actor": ..., "critic": ...}
    opt_state: Any
    env_state: Any
    obs: jax.Array  # [N, obs_size] normalised observation to act on (placeholders before a deferred start)
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
    task_metrics: dict[str, jax.Array]  # each of the task's own metrics (`task/<name>`), its mean over the rollout's steps


@struct.dataclass
class Transition:
    """One rollout step of every environment; a leading [T] axis after the rollout."""

    obs: jax.Array
    final_obs: jax.Array
    action: jax.Array
    log_prob: jax.Array
    reward: jax.Array
    terminated: jax.Array
    truncated: jax.Array
    episode_return: jax.Array
    episode_length: jax.Array
    task_metrics: dict[str, jax.Array]  # what the environment reports beside the step (`info["task/<name>"]`)


# ---------------------------------------------------------------- the trainer


@dataclasses.dataclass(frozen=True)
class Trainer:
    """The static parts of one training run, and its pure, jittable entry points.

    `init(key, hparams=None)` builds the state; `update(state)` is one update; `train(key,
    hparams=None)` the whole run (what `make_train` returns); `scan_updates(state, n)` does n
    updates in one `lax.scan`. The command line calls one compiled chunk of `scan_updates(state,
    n, diagnose=True)` repeatedly (all chunks the same length, so it compiles once) to report
    progress between chunks."""

    config: Config
    env: envs.NormalizeObservation  # the wrapped, batched environment that training steps
    actor: Actor
    critic: Critic
    optimizer: optax.GradientTransformation
    axis_name: str | None = None  # the device axis one run's environments are split over, if any

    def init(self, key: jax.Array, hparams: Hyperparams | None = None) -> TrainState:
        """The state before the first update: fresh networks, optimiser and environments;
        `hparams` default to the config's values."""
        hparams = Hyperparams.from_config(self.config) if hparams is None else hparams
        key, actor_key, critic_key, env_key = jax.random.split(key, 4)
        dummy_obs = jnp.zeros((self.env.spec.observation_size,))
        params = {"actor": self.actor.init(actor_key, dummy_obs), "critic": self.critic.init(critic_key, dummy_obs)}
        env_state, ts = self.env.reset(device_key(env_key, self.axis_name))
        zero = jnp.zeros(())
        opt_state = optimizer.set_learning_rate(self.optimizer.init(params), hparams.lr)
        return TrainState(
            params, opt_state, env_state, ts.obs, key, jnp.zeros((), jnp.int32), hparams,
            envs.RunningMeanStd.zeros(()), zero, zero,
        )  # fmt: skip

    def update(self, state: TrainState, diagnose: bool = False) -> tuple[TrainState, Any]:
        """One update (Algorithm 1's outer loop body): collect a rollout, then learn from it. The
        metrics, or with `diagnose` (the command line's) the metrics and the update's `Diagnostics`."""
        return (diagnosed_learn if diagnose else learn)(self, collect(self, state))

    def train(self, key: jax.Array, hparams: Hyperparams | None = None) -> tuple[TrainState, Metrics]:
        """The whole run, `config.num_updates` updates from `init(key, hparams)`: the final state
        and each update's metrics. Jittable and vmappable, as `make_train`'s function."""
        return self.scan_updates(self.init(key, hparams), self.config.num_updates)

    def scan_updates(self, state: TrainState, num_updates: int, diagnose: bool = False) -> tuple[TrainState, Any]:
        """`num_updates` updates in one `lax.scan`: the state after them and each update's outputs
        (`update`'s, with a leading [num_updates] axis). The command line runs it a chunk at a time."""
        return jax.lax.scan(lambda s, _: self.update(s, diagnose), state, None, length=num_updates)

    def restart_episodes(self, state: TrainState) -> TrainState:
        """`state` with a fresh episode in every environment; parameters, optimiser, counters
        and the normalisers' statistics stay. A resumed run needs this for host-side simulators,
        whose state lives outside JAX and so in no checkpoint."""
        key, reset_key = jax.random.split(state.key)
        env_state, ts = self.env.restart(state.env_state, device_key(reset_key, self.axis_name))
        return state.replace(env_state=env_state, obs=ts.obs, key=key)

    def close(self) -> None:
        """Frees the host simulators that training built, if any: no state of this trainer's is
        stepped after it."""
        batched = self.env
        while not isinstance(batched, envs.BatchedEnv):  # the batch wrappers, down to the batch
            batched = batched.env
        if isinstance(batched, envs.BatchedHostEnv):
            batched.close()

    def observation_statistics(self, state: TrainState) -> envs.RunningMeanStd:
        """The observation normaliser's statistics, which a saved policy needs."""
        return self.env.statistics(state.env_state)


def make_trainer(config: Config, env: envs.Env, axis_name: str | None = None, env_shards: int = 1) -> Trainer:
    """The trainer of `config` on `env`; with `axis_name`, one device's part of a run whose
    environments are split in `env_shards` equal shares over that device axis. A bad config is
    refused (UsageError)."""
    config = config.validate()
    actor, critic = make_networks(config, env.spec)
    wrapped = wrap_for_training(env, config, env_shards, axis_name)
    return Trainer(config, wrapped, actor, critic, optimizer.make_optimizer(config), axis_name)


def make_train(config: Config, env: envs.Env) -> Callable[..., tuple[TrainState, Metrics]]:
    """`train(key, hparams=None) -> (final state, per-update metrics)`: the whole run,
    jittable and vmappable. `jax.vmap(train)(keys, hparams)` with [R]-leaved `Hyperparams`
    trains a sweep of R runs (grid points x seeds) in one program. `make_trainer(config, env).train`
    is the same function, with the trainer that `make_policy` and `save_run` take."""
    return make_trainer(config, env).train


# ---------------------------------------------------------------- one update: collect, then learn


@struct.dataclass
class Collected:
    """An update's first half, for its minibatch epochs: the state after the rollout (its key
    moved on, this update's learning rate set, the return statistics updated), the batch [B],
    the epochs' key, the rollout's finished episodes (`finished_episodes`), its count of
    non-finite numbers (`diagnostics.count_rollout`) and its task metrics' means. `--split-epochs` runs `collect` and `learn`
    on different devices, so this is all that passes between them."""

    state: TrainState
    batch: Batch
    epochs_key: jax.Array
    episodes: tuple[jax.Array, jax.Array, jax.Array]
    rollout_counts: tuple[jax.Array, jax.Array]
    task_metrics: dict[str, jax.Array]


def collect(trainer: Trainer, state: TrainState) -> Collected:
    """The rollout under the current policy and its batch of advantages and returns."""
    config = trainer.config
    key, rollout_key, epochs_key = jax.random.split(state.key, 3)
    opt_state = optimizer.annealed(config, state.opt_state, state.hparams.lr, state.update)
    env_state, obs, traj = rollout(trainer, state.params, state.env_state, state.obs, rollout_key)
    batch, value_stats = make_batch(trainer, state.params, traj, state.value_stats)
    episodes = finished_episodes(traj, state, trainer.axis_name)
    state = state.replace(opt_state=opt_state, env_state=env_state, obs=obs, key=key, value_stats=value_stats)
    task_metrics = {name: value.mean() for name, value in traj.task_metrics.items()}
    if trainer.axis_name is not None:
        task_metrics = jax.lax.pmean(task_metrics, trainer.axis_name)
    return Collected(state, batch, epochs_key, episodes, diagnostics.count_rollout(traj, config), task_metrics)


def diagnosed_learn(trainer: Trainer, collected: Collected) -> tuple[TrainState, tuple[Metrics, diagnostics.Diagnostics]]:
    """`learn`, with the update's `Diagnostics` (the rollout's and the new state's non-finite counts) beside its metrics."""
    state, metrics = learn(trainer, collected)
    return state, (metrics, diagnostics.Diagnostics.of(collected.rollout_counts, state, trainer.config))


def learn(trainer: Trainer, collected: Collected) -> tuple[TrainState, Metrics]:
    """The minibatch epochs on a collected batch: the state after the update, and its metrics."""
    state, (episode_return, episode_length, finished) = collected.state, collected.episodes
    params, opt_state, loss_metrics = minibatch_epochs(
        trainer, state.hparams, state.params, state.opt_state, collected.batch, collected.epochs_key
    )
    update_count = state.update + 1
    metrics = Metrics(
        env_steps=update_count * trainer.config.batch_size,
        episode_return=episode_return,
        episode_length=episode_length,
        episodes_finished=finished,
        action_std=mean_scale(trainer.actor, params["actor"], collected.batch.obs),
        learning_rate=state.opt_state.hyperparams["learning_rate"],
        task_metrics=collected.task_metrics,
        **{name: getattr(loss_metrics, name).mean() for name in LossMetrics.__dataclass_fields__},
    )
    new_state = state.replace(
        params=params, opt_state=opt_state, update=update_count,
        last_episode_return=episode_return, last_episode_length=episode_length,
    )  # fmt: skip
    return new_state, metrics


def rollout(trainer: Trainer, params: dict, env_state: Any, obs: jax.Array, key: jax.Array) -> tuple[Any, jax.Array, Transition]:
    """`num_steps` steps of every environment under the unperturbed policy. Returns the
    environments' state and observation after them, and the transitions [T, N]."""

    def step(params, carry, key):
        env_state, obs = carry
        loc, log_scale = trainer.actor.apply(params["actor"], obs)
        action, log_prob = policy_distribution(loc, log_scale, trainer.config.dist).sample_and_log_prob(seed=key)
        env_state, ts = trainer.env.step(env_state, to_action(action, trainer.config.dist, *bounds))
        transition = Transition(
            obs, ts.final_obs, action, log_prob, ts.reward, ts.terminated, ts.truncated,
            ts.info["episode_return"], ts.info["episode_length"],
            {name[len("task/") :]: value for name, value in ts.info.items() if name.startswith("task/")},
        )  # fmt: skip
        return (env_state, ts.obs), transition

    bounds = jnp.asarray(trainer.env.spec.action_low), jnp.asarray(trainer.env.spec.action_high)
    starts_key, key = jax.random.split(device_key(key, trainer.axis_name))
    # Episodes that end in this rollout restart from initial states drawn here, once; in the
    # first rollout every environment starts from them (`VectorEnv`'s deferred start).
    env_state, start = trainer.env.draw_starts(env_state, starts_key)
    obs = jnp.where(start.started, start.obs, obs)
    keys = jax.random.split(key, trainer.config.num_steps)
    (env_state, obs), traj = jax.lax.scan(functools.partial(step, params), (env_state, obs), keys)
    return env_state, obs, traj


def make_batch(
    trainer: Trainer, params: dict, traj: Transition, value_stats: envs.RunningMeanStd
) -> tuple[Batch, envs.RunningMeanStd]:
    """Values, GAE and the batch [B = T * N] of one rollout; with `normalize_value`, the
    critic's targets on the scale of return statistics updated with this rollout's returns."""
    config, critic = trainer.config, trainer.critic
    # Values in large batched calls after the rollout rather than one per step. A step's next
    # observation is the following step's observation unless its episode ended there.
    values = critic.apply(params["critic"], traj.obs)
    last_values = critic.apply(params["critic"], traj.final_obs[-1])
    next_values = jnp.concatenate([values[1:], last_values[None]])
    if config.truncation == "bootstrap":
        next_values = bootstrapped_next_values(critic, params, traj, next_values)
    if config.normalize_value:
        values, next_values = value_stats.unstandardize(values), value_stats.unstandardize(next_values)
    advantages, returns = compute_gae(
        traj.reward, values, next_values, traj.terminated, traj.truncated, config.gamma, config.gae_lambda,
        config.truncation,
    )  # fmt: skip
    if config.normalize_value:
        # The critic learns the new returns on the scale of statistics that include them.
        value_stats = value_stats.update(returns.reshape(-1), trainer.axis_name)
        values, returns = value_stats.standardize(values), value_stats.standardize(returns)
    batch = jax.tree.map(
        lambda x: x.reshape(-1, *x.shape[2:]),
        Batch(traj.obs, traj.action, traj.log_prob, values, advantages, returns),
    )
    return batch, value_stats


def bootstrapped_next_values(critic: Critic, params: dict, traj: Transition, next_values: jax.Array) -> jax.Array:
    """Next values [T, N] with each truncated step's taken from its final observation's value.

    Only a bootstrapped truncation reads the value of a final observation, so the critic's pass
    over all final observations runs only in a rollout where some episode was truncated."""
    final_values = jax.lax.cond(traj.truncated.any(), lambda: critic.apply(params["critic"], traj.final_obs), lambda: next_values)
    return jnp.where(traj.truncated, final_values, next_values)


def finished_episodes(
    traj: Transition, state: TrainState, axis_name: str | None = None
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Mean return and length of the episodes that ended in this rollout (the previous
    update's where none did), and how many ended; with `axis_name`, over all its devices."""
    sums = (traj.terminated | traj.truncated).sum(), traj.episode_return.sum(), traj.episode_length.sum()
    if axis_name is not None:
        sums = jax.lax.psum(sums, axis_name)
    finished, return_sum, length_sum = sums
    any_finished = finished > 0
    denominator = jnp.maximum(finished, 1)
    episode_return = jnp.where(any_finished, return_sum / denominator, state.last_episode_return)
    episode_length = jnp.where(any_finished, length_sum / denominator, state.last_episode_length)
    return episode_return, episode_length, finished


def minibatch_epochs(
    trainer: Trainer, hparams: Hyperparams, params: dict, opt_state: Any, batch: Batch, key: jax.Array
) -> tuple[dict, Any, LossMetrics]:
    """`update_epochs` passes over `batch`, each in `num_minibatches` shuffled minibatches.
    With a device axis, each device shuffles its own share of the batch and takes its share of
    every minibatch from it, so over an epoch every sample is used once, as on one device.
    Returns the parameters, the optimiser state and the loss metrics [epochs, minibatches]."""
    config = trainer.config

    def minibatch(carry, inputs):
        params, opt_state = carry
        params, opt_state, metrics = gradient_step(trainer, hparams, params, opt_state, *inputs)
        return (params, opt_state), metrics

    # The batch is read by every epoch and changed by none: closed over, not carried.
    def epoch(carry, key):
        permute_key, loss_key = (device_key(k, trainer.axis_name) for k in jax.random.split(key))
        permutation = shuffled_indices(permute_key, batch.obs.shape[0])
        minibatches = jax.tree.map(
            lambda x: x[permutation].reshape(config.num_minibatches, -1, *x.shape[1:]),
            batch,
        )
        loss_keys = jax.random.split(loss_key, config.num_minibatches)
        return jax.lax.scan(minibatch, carry, (minibatches, loss_keys))

    keys = jax.random.split(key, config.update_epochs)
    (params, opt_state), metrics = jax.lax.scan(epoch, (params, opt_state), keys)
    return params, opt_state, metrics


def gradient_step(
    trainer: Trainer, hparams: Hyperparams, params: dict, opt_state: Any, batch: Batch, key: jax.Array
) -> tuple[dict, Any, LossMetrics]:
    """One optimiser step on one minibatch, and the adaptive learning rate's adjustment. With a
    device axis, the gradients and loss metrics are the means over the devices' shares of the
    minibatch, so every device takes the same step."""
    config, axis_name = trainer.config, trainer.axis_name
    grads, metrics = jax.grad(ppo_loss, has_aux=True)(
        params, trainer.actor, trainer.critic, batch, key, config, hparams, axis_name
    )
    if axis_name is not None:
        grads, metrics = jax.lax.pmean((grads, metrics), axis_name)
    updates, opt_state = trainer.optimizer.update(grads, opt_state, params)
    params = optax.apply_updates(params, updates)
    return params, optimizer.adapted(config, opt_state, metrics.approx_kl), metrics


# ---------------------------------------------------------------- the parts the trainer is built from


def make_networks(config: Config, spec: envs.EnvSpec) -> tuple[Actor, Critic]:
    """The trainer's networks, each reading its part of the environment's observation."""
    critic_sizes = tuple(config.critic_hidden_sizes or config.hidden_sizes)
    return make_actor(config, spec), Critic(critic_sizes, config.activation, spec.part(spec.critic_obs_key))


def device_key(key: jax.Array, axis_name: str | None) -> jax.Array:
    """`key` folded with the device's index on `axis_name`, for draws that must differ between
    the devices that share a run; `key` itself without an axis."""
    return key if axis_name is None else jax.random.fold_in(key, jax.lax.axis_index(axis_name))
