"""Actor and critic networks, the policy distribution and RPO's perturbation of its location."""

from __future__ import annotations

from typing import Sequence

import distrax
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from rpo_jax.config import MIN_SCALE, TANH_NORMAL

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
    """obs [..., obs_size] -> (location [..., action_size], log_scale [action_size] or [..., action_size]).

    The log-scale is one state-independent parameter vector, initialised to `init_log_scale`;
    with `state_dependent_scale` (Brax's policy, `TANH_NORMAL`) it is an output of the network
    instead: the last layer gives 2 x action_size numbers, the location and s, and the scale is
    softplus(s) + MIN_SCALE (about 0.69 at the start, where s is near 0). `reads`: the part of the
    observation it reads (`EnvSpec.part`), so that it never sees the critic's."""

    action_size: int
    hidden_sizes: Sequence[int] = (64, 64)
    activation: str = "tanh"
    reads: tuple[int, int] | None = None
    init_log_scale: float = 0.0
    state_dependent_scale: bool = False

    @nn.compact
    def __call__(self, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        outputs = self.action_size * (2 if self.state_dependent_scale else 1)
        loc = MLP(self.hidden_sizes, self.activation, outputs, 0.01)(read(obs, self.reads))
        if self.state_dependent_scale:
            loc, scale_input = jnp.split(loc, 2, axis=-1)
            return loc, jnp.log(jax.nn.softplus(scale_input) + MIN_SCALE)
        log_scale = self.param("log_std", nn.initializers.constant(self.init_log_scale), (self.action_size,))
        return loc, log_scale


def mean_scale(actor: Actor, actor_params: dict, obs: jax.Array) -> jax.Array:
    """The policy's scale averaged over action dimensions (and, where it depends on the state,
    over the observations `obs` [..., obs_size])."""
    if not actor.state_dependent_scale:
        return jnp.exp(actor_params["params"]["log_std"]).mean()
    return jnp.exp(actor.apply(actor_params, obs)[1]).mean()


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


def policy_distribution(loc: jax.Array, log_scale: jax.Array, kind: str = "gaussian") -> distrax.Distribution | TanhNormal:
    """Factorised `kind` distribution over [..., action_size] with location `loc` and scale
    exp(log_scale); log_prob, entropy and KL sum over action dimensions."""
    if kind == TANH_NORMAL:
        return TanhNormal(loc, jnp.exp(log_scale))
    return distrax.Independent(DISTRIBUTIONS[kind](loc, jnp.exp(log_scale)), reinterpreted_batch_ndims=1)


class TanhNormal:
    """Brax's `NormalTanhDistribution`: a factorised Gaussian over an unbounded u [..., action_size]
    whose action is tanh(u). As in Brax, samples, stored actions and log-probabilities are of u
    (tanh saturates, so u could not be recovered from the action): log p(u) is the Gaussian's less
    log|d tanh(u)/du| = 2 (log 2 - u - softplus(-2u)), the density of tanh(u) at the action. The
    squashed distribution's entropy has no closed form; `entropy(seed)` is Brax's one-sample
    estimate, the Gaussian's entropy plus that log-Jacobian at one draw of u. KL divergences are
    the Gaussians' (a bijection leaves them unchanged). `to_action` maps tanh(u) onto the bounds."""

    def __init__(self, loc: jax.Array, scale: jax.Array):
        self.loc = loc
        self.normal = distrax.Independent(distrax.Normal(loc, scale), reinterpreted_batch_ndims=1)

    def sample(self, seed: jax.Array) -> jax.Array:
        return self.normal.sample(seed=seed)

    def log_prob(self, u: jax.Array) -> jax.Array:
        return self.normal.log_prob(u) - tanh_log_jacobian(u)

    def sample_and_log_prob(self, seed: jax.Array) -> tuple[jax.Array, jax.Array]:
        u = self.sample(seed)
        return u, self.log_prob(u)

    def entropy(self, seed: jax.Array) -> jax.Array:
        return self.normal.entropy() + tanh_log_jacobian(self.sample(seed))

    def kl_divergence(self, other: TanhNormal) -> jax.Array:
        return self.normal.kl_divergence(other.normal)


def tanh_log_jacobian(u: jax.Array) -> jax.Array:
    """log|d tanh(u)/du| summed over the last axis, in the form that stays finite for large |u|."""
    return (2.0 * (jnp.log(2.0) - u - jax.nn.softplus(-2.0 * u))).sum(-1)


def policy_entropy(dist: distrax.Distribution | TanhNormal, seed: jax.Array) -> jax.Array:
    """The entropy of a policy distribution [...]: closed-form for the paper's families, Brax's
    one-sample estimate from `seed` for `TanhNormal`."""
    return dist.entropy(seed) if isinstance(dist, TanhNormal) else dist.entropy()


def to_action(sample: jax.Array, kind: str, low: jax.Array, high: jax.Array) -> jax.Array:
    """The environment's action for a sample (or the location) of a `kind` policy: tanh-normal's
    squashed onto [low, high] (low + (tanh(u) + 1) (high - low) / 2: tanh(u) itself where the
    bounds are [-1, 1], as in Brax); the others' as drawn, which the environment clips."""
    if kind != TANH_NORMAL:
        return sample
    centre, half_width = (high + low) / 2, (high - low) / 2
    return centre + half_width * jnp.tanh(sample)


def perturb_location(loc: jax.Array, key: jax.Array, alpha: float | jax.Array) -> jax.Array:
    """RPO: loc + z with z ~ U(-alpha, alpha), independent per sample and action dimension.

    With alpha = 0, z is exactly 0 and so is the change, which makes RPO(0) bit-identical to
    PPO while consuming the same random keys."""
    return loc + jax.random.uniform(key, loc.shape, loc.dtype, minval=-alpha, maxval=alpha)
