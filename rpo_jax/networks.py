"""Actor and critic networks, the policy distribution and RPO's perturbation of its location."""

from __future__ import annotations

from typing import Sequence

import distrax
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

ACTIVATIONS = {"tanh": nn.tanh, "relu": nn.relu, "elu": nn.elu, "silu": nn.silu}


def orthogonal(gain: float, iterations: int = 60) -> nn.initializers.Initializer:
    """Orthogonal initialiser (Haar-distributed, scaled by `gain`) computed with matmuls only.

    The orthogonal polar factor of a Gaussian matrix is Haar-distributed, like the Q of its QR
    factorisation. Newton-Schulz iterations X <- 1.5 X - 0.5 X X^T X converge to it from
    X / ||X||_F. QR would be a LAPACK call, and under `jax.vmap` (several seeds in one program)
    jaxlib 0.10's CPU build runs batched LAPACK calls on a shared thread pool where two of them
    can wait on each other forever; matmuls batch without that risk, on every backend. Sixty
    iterations reach float32 precision for condition numbers far beyond those of Gaussian
    matrices of network sizes."""

    def init(key: jax.Array, shape: tuple[int, ...], dtype=jnp.float32) -> jax.Array:
        rows, cols = shape
        tall = rows >= cols
        x = jax.random.normal(key, shape if tall else (cols, rows), jnp.float32)
        x = x / jnp.linalg.norm(x)
        x = jax.lax.fori_loop(0, iterations, lambda _, x: 1.5 * x - 0.5 * x @ (x.T @ x), x)
        return (gain * (x if tall else x.T)).astype(dtype)

    return init


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
            x = act(nn.Dense(size, kernel_init=orthogonal(np.sqrt(2)))(x))
        return nn.Dense(self.out_size, kernel_init=orthogonal(self.head_gain))(x)


def read(obs: jax.Array, part: tuple[int, int] | None) -> jax.Array:
    """The part [start, stop) of observations [..., obs_size] that a network reads (all: None)."""
    return obs if part is None else obs[..., part[0] : part[1]]


class Actor(nn.Module):
    """obs [..., obs_size] -> (location [..., action_size], log_scale [action_size]).

    The log-scale is one state-independent parameter vector, initialised to `init_log_scale`.
    `reads`: the part of the observation it reads (`EnvSpec.part`), so that it never sees the
    critic's."""

    action_size: int
    hidden_sizes: Sequence[int] = (64, 64)
    activation: str = "tanh"
    reads: tuple[int, int] | None = None
    init_log_scale: float = 0.0

    @nn.compact
    def __call__(self, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        loc = MLP(self.hidden_sizes, self.activation, self.action_size, 0.01)(read(obs, self.reads))
        log_scale = self.param("log_std", nn.initializers.constant(self.init_log_scale), (self.action_size,))
        return loc, log_scale


def actor_log_scale(actor_params: dict) -> jax.Array:
    """The actor's state-independent log-scale [action_size], read from its parameters."""
    return actor_params["params"]["log_std"]


class Critic(nn.Module):
    """obs [..., obs_size] -> value [...], from the part `reads` (a privileged state)."""

    hidden_sizes: Sequence[int] = (64, 64)
    activation: str = "tanh"
    reads: tuple[int, int] | None = None

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:
        return MLP(self.hidden_sizes, self.activation, 1, 1.0)(read(obs, self.reads))[..., 0]


# Location-scale families the paper compares. distrax gives each an exact log-probability,
# a closed-form entropy (Gaussian 1/2 log(2 pi e s^2), Laplace 1 + log 2b, Gumbel
# log b + Euler's gamma + 1) and a closed-form KL between two members of the family.
DISTRIBUTIONS = {"gaussian": distrax.Normal, "laplace": distrax.Laplace, "gumbel": distrax.Gumbel}


def policy_distribution(loc: jax.Array, log_scale: jax.Array, kind: str = "gaussian") -> distrax.Distribution:
    """Factorised `kind` distribution over [..., action_size] with location `loc` and scale
    exp(log_scale); log_prob, entropy and KL sum over action dimensions."""
    return distrax.Independent(DISTRIBUTIONS[kind](loc, jnp.exp(log_scale)), reinterpreted_batch_ndims=1)


def perturb_location(loc: jax.Array, key: jax.Array, alpha: float | jax.Array) -> jax.Array:
    """RPO: loc + z with z ~ U(-alpha, alpha), independent per sample and action dimension.

    With alpha = 0, z is exactly 0 and so is the change, which makes RPO(0) bit-identical to
    PPO while consuming the same random keys."""
    return loc + jax.random.uniform(key, loc.shape, loc.dtype, minval=-alpha, maxval=alpha)
