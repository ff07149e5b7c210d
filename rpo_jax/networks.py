"""Actor and critic networks, the policy distribution and RPO's perturbation of its location."""

from __future__ import annotations

from typing import Sequence

import distrax
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

ACTIVATIONS = {"tanh": nn.tanh, "relu": nn.relu, "elu": nn.elu, "silu": nn.silu}


class MLP(nn.Module):
    """Hidden layers with orthogonal init (gain sqrt 2), then a linear head of `head_gain`."""

    hidden_sizes: Sequence[int]
    activation: str
    out_size: int
    head_gain: float

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        act = ACTIVATIONS[self.activation]
        for size in self.hidden_sizes:
            x = act(nn.Dense(size, kernel_init=nn.initializers.orthogonal(np.sqrt(2)))(x))
        return nn.Dense(self.out_size, kernel_init=nn.initializers.orthogonal(self.head_gain))(x)


class Actor(nn.Module):
    """obs [..., obs_size] -> (location [..., action_size], log_scale [action_size]).

    The log-scale is one state-independent parameter vector, initialised to 0."""

    action_size: int
    hidden_sizes: Sequence[int] = (64, 64)
    activation: str = "tanh"

    @nn.compact
    def __call__(self, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        loc = MLP(self.hidden_sizes, self.activation, self.action_size, 0.01)(obs)
        log_scale = self.param("log_std", nn.initializers.zeros, (self.action_size,))
        return loc, log_scale


class Critic(nn.Module):
    """obs [..., obs_size] -> value [...]."""

    hidden_sizes: Sequence[int] = (64, 64)
    activation: str = "tanh"

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:
        return MLP(self.hidden_sizes, self.activation, 1, 1.0)(obs)[..., 0]


def policy_distribution(loc: jax.Array, log_scale: jax.Array) -> distrax.Distribution:
    """Diagonal Gaussian over [..., action_size]; log_prob and entropy sum over action dims."""
    return distrax.Independent(distrax.Normal(loc, jnp.exp(log_scale)), reinterpreted_batch_ndims=1)


def perturb_location(loc: jax.Array, key: jax.Array, alpha: float | jax.Array) -> jax.Array:
    """RPO: loc + z with z ~ U(-alpha, alpha), independent per sample and action dimension.

    With alpha = 0, z is exactly 0 and so is the change, which makes RPO(0) bit-identical to
    PPO while consuming the same random keys."""
    return loc + jax.random.uniform(key, loc.shape, loc.dtype, minval=-alpha, maxval=alpha)
