"""Forms of operations that XLA's CPU backend runs slowly, rewritten to run fast there. Each gives
the same distribution as the plain form; none changes what the algorithm does."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def shuffled_indices(key: jax.Array, n: int) -> jax.Array:
    """A uniformly random permutation of range(n), int32 [n]: the order the minibatch epochs take
    the batch in (`rpo_jax.ppo.minibatch_epochs`).

    Why not `jax.random.permutation`: it sorts random keys with the indices as values, and XLA's
    CPU backend sorts one array of integers up to 6 times faster than keys with values; the epochs
    of 4096 environments spent a third of their time sorting. So each round sorts random bits
    packed above the indices' bits (every packed key distinct) and reads the order from the low
    bits. Over the rounds the random bits add up to 3 x log2(n), as jax's rounds do, so ties, which
    keep the previous round's order, have a chance below 1/n. Rounds grow with n: 2 at 2**11
    samples, 4 at 2**17, 11 at 2**25."""
    index_bits = max(1, (n - 1).bit_length())
    random_bits = 32 - index_bits
    positions = jnp.arange(n, dtype=jnp.uint32)
    order = positions
    for round_key in jax.random.split(key, -(-3 * index_bits // random_bits)):
        packed = (jax.random.bits(round_key, (n,), jnp.uint32) << index_bits) | positions
        order = order[jax.lax.sort(packed) & ((1 << index_bits) - 1)]
    return order.astype(jnp.int32)
