"""The optimiser and the learning-rate schedules, in one place: global-norm clipping then Adam,
with the learning rate held in the optimiser's state (`make_optimizer`), set before each update
by the linear schedule (`annealed`) and after each gradient step by rl_games' adaptive one
(`adapted`); a constant schedule leaves it. Population-based training sets it too
(`set_learning_rate`)."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import optax

from rpo_jax.config import Config


def make_optimizer(config: Config) -> optax.GradientTransformation:
    """Global-norm clipping (none where max_grad_norm is 0) then Adam, with the learning rate held
    in the state so that the linear and adaptive schedules set it between steps."""

    def chain(learning_rate):
        clip = optax.clip_by_global_norm(config.max_grad_norm) if config.max_grad_norm else optax.identity()
        return optax.chain(clip, optax.adam(learning_rate, eps=config.adam_eps))

    return optax.inject_hyperparams(chain)(learning_rate=config.lr)


def set_learning_rate(opt_state: Any, lr: jax.Array) -> Any:
    return opt_state._replace(hyperparams={**opt_state.hyperparams, "learning_rate": lr})


def annealed(config: Config, opt_state: Any, lr: jax.Array, update: jax.Array) -> Any:
    """Before update `update` (0-based): the linear schedule's rate, `lr` annealed to 0 over the run."""
    if config.lr_schedule != "linear":
        return opt_state
    return set_learning_rate(opt_state, lr * (1.0 - update / config.num_updates))


def adapted(config: Config, opt_state: Any, approx_kl: jax.Array) -> Any:
    """After a gradient step: the adaptive schedule's rate, divided by 1.5 (to 1e-6 at least) where
    the step's approximate KL exceeded twice `kl_target`, multiplied by 1.5 (to 1e-2 at most) where
    it fell below half of it."""
    if config.lr_schedule != "adaptive":
        return opt_state
    lr = opt_state.hyperparams["learning_rate"]
    lr = jnp.where(approx_kl > 2 * config.kl_target, jnp.maximum(lr / 1.5, 1e-6), lr)
    lr = jnp.where(approx_kl < 0.5 * config.kl_target, jnp.minimum(lr * 1.5, 1e-2), lr)
    return set_learning_rate(opt_state, lr)
